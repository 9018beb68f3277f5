"""Events as torch tensors: one window, or a padded batch of windows (:class:`EventBatch`).

Inside torch, one window's events are an :class:`EventBatch`: ``xy`` float (N, 2) in pixels, ``t``
float32 seconds relative to a reference time (absolute microseconds in float32 would lose
sub-millisecond precision after a few seconds), ``p`` float (N,). Torch is imported on first use, so
that NumPy-only code (level one) that imports :mod:`evseg_torch.events` never loads it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from evseg_torch.errors import EventFormatError
from evseg_torch.events.format import EVENT_DTYPE

if TYPE_CHECKING:
    import torch


class EventBatch(NamedTuple):
    """Events as torch tensors: one window, or a padded batch of windows.

    One window: ``xy`` :math:`(N, 2)`, ``t`` :math:`(N,)`, ``p`` :math:`(N,)` and ``lengths`` ``None``.
    A batch of B windows (the one batch form of evseg_torch, built by :func:`batch_windows`): each field
    gains a leading batch dimension and is padded to the longest window, ``xy`` :math:`(B, N_{max}, 2)`,
    ``t`` and ``p`` :math:`(B, N_{max})`, and ``lengths`` int64 :math:`(B,)` counts each window's real
    events; padding sits at the end of each row, with every field 0 there (``p`` = 0 is no polarity).

    Attributes:
        xy: pixel coordinates, ``x`` the column and ``y`` the row.
        t: seconds relative to each window's reference time.
        p: polarity in {-1, +1} (0 for padding).
        lengths: events per window of a batch; ``None`` for one window.

    ``len()`` is the size of the first dimension: the number of events of one window, the number of
    windows of a batch.
    """

    xy: torch.Tensor
    t: torch.Tensor
    p: torch.Tensor
    lengths: torch.Tensor | None = None

    @property
    def is_batched(self) -> bool:
        """Whether this is a padded batch of windows."""
        return self.lengths is not None

    @property
    def mask(self) -> torch.Tensor:
        """Which entries are real events (bool): :math:`(B, N_{max})` for a batch, :math:`(N,)` else."""
        import torch

        if self.lengths is None:
            return torch.ones(self.t.shape, dtype=torch.bool, device=self.t.device)
        return torch.arange(self.t.shape[-1], device=self.t.device) < self.lengths[:, None]

    def to(self, *args, **kwargs) -> EventBatch:
        """Move or cast the event tensors, as :meth:`torch.Tensor.to` does; ``lengths`` only moves."""
        xy, t, p = (tensor.to(*args, **kwargs) for tensor in (self.xy, self.t, self.p))
        lengths = None if self.lengths is None else self.lengths.to(device=xy.device)
        return EventBatch(xy, t, p, lengths)

    def unbatch(self) -> list[EventBatch]:
        """The windows of a batch, each without its padding (views, not copies)."""
        if self.lengths is None:
            raise EventFormatError("unbatch needs a padded batch of windows (lengths given), got one window")
        return [
            EventBatch(self.xy[row, :count], self.t[row, :count], self.p[row, :count])
            for row, count in enumerate(self.lengths.tolist())
        ]

    def __len__(self) -> int:  # a NamedTuple's len would be 4, the number of fields
        return int(self.t.shape[0])


def _make_event_batch(cls, iterable) -> EventBatch:
    fields = tuple(iterable)
    if len(fields) != len(cls._fields):
        raise TypeError(f"EventBatch takes {len(cls._fields)} fields, got {len(fields)}")
    return tuple.__new__(cls, fields)


# NamedTuple's own _make, behind _replace, checks len() against the 4 fields, which __len__ changed; a
# NamedTuple's class body may not redefine it.
EventBatch._make = classmethod(_make_event_batch)


def batch_windows(windows: Sequence[EventBatch]) -> EventBatch:
    """Pad windows into one batch (see :class:`EventBatch`).

    Args:
        windows: B single windows, all of one dtype and on one device.

    Returns:
        The padded batch, ``lengths`` the windows' event counts.

    Raises:
        EventFormatError: no windows, a window that is itself a batch, or windows whose fields are not
            ``xy`` :math:`(N, 2)`, ``t`` and ``p`` :math:`(N,)`.

    Examples:
        >>> import torch
        >>> one = EventBatch(torch.zeros(3, 2), torch.zeros(3), torch.ones(3))
        >>> two = EventBatch(torch.ones(1, 2), torch.zeros(1), -torch.ones(1))
        >>> batch = batch_windows([one, two])
        >>> batch.xy.shape, batch.lengths.tolist(), batch.p[1].tolist()
        (torch.Size([2, 3, 2]), [3, 1], [-1.0, 0.0, 0.0])
    """
    import torch

    windows = list(windows)
    if not windows:
        raise EventFormatError("batch_windows needs at least one window, got none")
    for index, window in enumerate(windows):
        if not isinstance(window, EventBatch) or window.is_batched:
            raise EventFormatError(f"window {index} is not a single EventBatch window")
        count = len(window)
        if window.xy.shape != (count, 2) or window.p.shape != (count,) or window.t.ndim != 1:
            raise EventFormatError(
                f"window {index} must have xy (N, 2), t (N,), p (N,); got {tuple(window.xy.shape)}, "
                f"{tuple(window.t.shape)}, {tuple(window.p.shape)}"
            )
    first = windows[0]
    lengths = torch.tensor([len(window) for window in windows], dtype=torch.int64, device=first.t.device)
    longest = int(lengths.max()) if len(windows) else 0
    xy = first.xy.new_zeros(len(windows), longest, 2)
    t = first.t.new_zeros(len(windows), longest)
    p = first.p.new_zeros(len(windows), longest)
    for row, window in enumerate(windows):
        count = len(window)
        xy[row, :count], t[row, :count], p[row, :count] = window.xy, window.t, window.p
    return EventBatch(xy, t, p, lengths)


def batch_of_one(events: EventBatch) -> EventBatch:
    """One window as a padded batch of one window (views of its tensors, ``lengths`` its event count)."""
    import torch

    lengths = torch.tensor([events.t.shape[-1]], device=events.t.device)
    return EventBatch(events.xy[None], events.t[None], events.p[None], lengths)


def to_torch(
    events: np.ndarray,
    t_ref_us: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> EventBatch:
    """Convert canonical events to an :class:`EventBatch`.

    Args:
        events: canonical structured array :math:`(N,)` (see :func:`as_events`).
        t_ref_us: reference time in microseconds; defaults to the first event's timestamp.
        device: torch device of the output.
        dtype: floating dtype of the output; defaults to float32.

    Returns:
        :class:`EventBatch` with ``t`` in seconds relative to ``t_ref_us`` (computed in int64 first,
        so no precision is lost to float32 absolute times).
    """
    import torch

    dtype = dtype or torch.float32
    if events.dtype != EVENT_DTYPE:
        raise EventFormatError(
            f"to_torch expects canonical events of dtype {EVENT_DTYPE}, got {events.dtype}"
        )
    t_ref = int(events["t"][0]) if t_ref_us is None and len(events) else int(t_ref_us or 0)
    t_rel = (events["t"] - t_ref).astype(np.float64) * 1e-6
    xy = np.column_stack([events["x"], events["y"]])
    return EventBatch(
        xy=torch.as_tensor(xy, dtype=dtype, device=device),
        t=torch.as_tensor(t_rel, dtype=dtype, device=device),
        p=torch.as_tensor(events["p"], dtype=dtype, device=device),
    )
