"""Level two's checks of its inputs, shared by its modules: each raises one of our errors naming the
problem (:mod:`evseg_torch.errors`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evseg_torch.errors import ConfigError, EventFormatError, ModelError, ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.motion import MotionModel

__all__ = [
    "check_blur",
    "check_events",
    "check_image",
    "check_labels",
    "check_padded_batch",
    "check_params",
    "check_points",
    "check_sensor_size",
]


def check_points(xy: Tensor, name: str) -> None:
    """``xy`` is a tensor of positions :math:`(..., N, 2)`; ``name`` names it in the error."""
    if not isinstance(xy, Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(xy).__name__}")
    if xy.ndim < 2 or xy.shape[-1] != 2:
        raise ShapeError(f"{name} must have shape (..., N, 2), got {tuple(xy.shape)}")


def check_sensor_size(sensor_size) -> tuple[int, int]:
    """``(H, W)`` as two positive ints (:class:`ShapeError` otherwise)."""
    try:
        height, width = (int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise ShapeError(f"sensor_size must be (H, W), got {sensor_size!r}") from None
    if height <= 0 or width <= 0:
        raise ShapeError(f"sensor_size (H, W) must be positive, got {sensor_size!r}")
    return height, width


def check_blur(sigma: float, truncate: float) -> None:
    """A Gaussian blur's ``sigma`` (finite, >= 0) and ``truncate`` (finite, > 0)."""
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ConfigError(f"sigma must be a finite number >= 0, got {sigma}")
    if not (math.isfinite(truncate) and truncate > 0):
        raise ConfigError(f"truncate must be a finite number > 0, got {truncate}")


def check_padded_batch(events: EventBatch) -> None:
    """``events`` is a padded batch of windows (:func:`~evseg_torch.events.batch_windows`)."""
    if not isinstance(events, EventBatch) or not events.is_batched:
        raise ShapeError("events must be a padded batch of windows (EventBatch with lengths)")
    if (
        events.t.ndim != 2
        or events.xy.shape != (*events.t.shape, 2)
        or events.lengths.shape != (events.t.shape[0],)
    ):
        raise ShapeError(
            "a padded batch must hold xy (B, N_max, 2), t (B, N_max) and lengths (B,), got "
            f"{tuple(events.xy.shape)}, {tuple(events.t.shape)} and {tuple(events.lengths.shape)}"
        )


def check_image(image: Tensor, name: str) -> None:
    """``image`` is a tensor :math:`(..., H, W)`; ``name`` names it in the error."""
    if not isinstance(image, Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim < 2:
        raise ShapeError(f"{name} must have shape (..., H, W), got {tuple(image.shape)}")


def check_events(events) -> EventBatch:
    """One non-empty window as level two takes it, an :class:`EventBatch` of ``xy`` :math:`(N, 2)`."""
    if not isinstance(events, EventBatch):
        raise EventFormatError(
            f"level two expects an EventBatch (see events.to_torch), got {type(events).__name__}"
        )
    count = len(events)
    if count == 0:
        raise EventFormatError("level two got a window with 0 events")
    if events.xy.shape != (count, 2) or events.p.shape != (count,):
        raise ShapeError(
            f"EventBatch fields must be xy (N, 2), t (N,), p (N,); got {tuple(events.xy.shape)}, "
            f"{tuple(events.t.shape)}, {tuple(events.p.shape)}"
        )
    return events


def check_params(params, events: EventBatch, model: MotionModel) -> Tensor:
    """A pool of finite models :math:`(K, P)`, K >= 1, for ``model``: a detached copy on the events'
    device and in their dtype."""
    if not isinstance(params, Tensor):
        raise ShapeError(f"init_params must be a torch.Tensor (K, P), got {type(params).__name__}")
    if params.ndim != 2 or params.shape[0] == 0 or params.shape[1] != model.n_params:
        raise ShapeError(
            f"init_params must be (K, {model.n_params}) with K >= 1 for the {model.name} "
            f"model, got {tuple(params.shape)}"
        )
    if not torch.isfinite(params).all():
        raise ModelError("init_params hold NaN or inf: every model's parameters must be finite")
    return params.detach().to(device=events.xy.device, dtype=events.xy.dtype).clone()


def check_labels(labels, events: EventBatch, params: Tensor) -> Tensor:
    """Integer labels :math:`(N,)` of the events, each indexing one of the models ``params``, as int64
    on the events' device."""
    labels = torch.as_tensor(labels, device=events.xy.device)
    if labels.shape != (len(events),) or labels.dtype.is_floating_point or labels.dtype == torch.bool:
        raise ShapeError(
            f"labels must be integers of shape ({len(events)},), got {labels.dtype} {tuple(labels.shape)}"
        )
    if len(labels) and (labels.min() < 0 or labels.max() >= params.shape[0]):
        raise ShapeError(f"labels must lie in [0, {params.shape[0]}) to index the {params.shape[0]} models")
    return labels.long()
