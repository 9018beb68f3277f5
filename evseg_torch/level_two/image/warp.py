"""The warp of fixed events as a linear map of the motion parameters, built once per fit.

Every motion model's velocity is linear in its parameters, ``v(x) = J(x) params``, so warping events
of fixed positions and times is ``x' = x - t J(x) params``: :class:`LinearWarp` stores ``t J(x)`` (and
its one-pixel differences, for the area element of the event-collapse guard) and each evaluation of a
fit is a few multiply-adds. Its backward pass sums over the events by blocks that padding cannot
change (:func:`sum_ignoring_padding`), so a cluster's gradient does not depend on the batch it is in.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from evseg_torch.errors import ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.checks import check_points
from evseg_torch.motion import MotionModel

__all__ = ["LinearWarp", "area_from", "area_gradient", "sum_ignoring_padding", "warp_events"]

# Values per block of sum_ignoring_padding: long enough for torch's fast sums, short enough that the
# zeros completing the last block cost little.
_SUM_BLOCK = 256


class LinearWarp(NamedTuple):
    """The warp of fixed events as a linear map of the parameters (``v = J(x) params``): built once,
    it turns every evaluation of an optimiser into a few multiply-adds.

    ``maps`` holds, parameter-first, :math:`(P, ..., N, C)`, what each parameter moves at each event:
    its displacement ``t J(x)`` (channels 0–1) and, with the area element (``C = 6``), the change of the
    warp's one-pixel steps ``t (J(x + e) - J(x))`` along ``e_x`` (channels 2–3) and ``e_y`` (4–5). One
    product of the maps and the parameters (:meth:`moved`) gives all of them.
    """

    xy: Tensor
    maps: Tensor

    @classmethod
    def build(cls, model: MotionModel, events: EventBatch, with_area: bool = True) -> LinearWarp:
        check_points(events.xy, "events.xy")
        if events.t.shape != events.xy.shape[:-1]:
            raise ShapeError(
                f"events.t must have shape {tuple(events.xy.shape[:-1])} to match events.xy, "
                f"got {tuple(events.t.shape)}"
            )
        t = events.t[..., None, None]
        jacobian = model.jacobian(events.xy)  # (..., N, 2, P)
        maps = [jacobian]
        if with_area:
            unit = torch.eye(2, dtype=events.xy.dtype, device=events.xy.device)
            maps += [model.jacobian(events.xy + e) - jacobian for e in unit]
        return cls(events.xy, (t * torch.cat(maps, dim=-2)).movedim(-1, 0).contiguous())

    def moved(self, params: Tensor) -> Tensor:
        """Each event's displacement and, with the area element, the changes of its one-pixel steps,
        :math:`(..., N, C)` for parameters :math:`(..., P)` (class docstring)."""
        return _apply(self.maps, params)

    def warped(self, params: Tensor) -> Tensor:
        """The warped events :math:`(..., N, 2)`."""
        return self.warped_from(self.moved(params))

    def warped_from(self, moved: Tensor) -> Tensor:
        return self.xy - moved[..., :2]

    def area(self, params: Tensor) -> Tensor:
        """The warp's area element ``det(dx'/dx)`` at each event, :math:`(..., N)`."""
        return area_from(self.moved(params))

    def rows(self, index: Tensor) -> LinearWarp:
        """The warp of some clusters of a gathered :math:`(K, N, 2)` warp: rows ``index``."""
        return LinearWarp(self.xy[index], self.maps[:, index])

    def params_gradient(self, grad_moved: Tensor) -> Tensor:
        """The gradient :math:`(..., P)` of a loss with respect to the parameters, from its gradient
        :math:`(..., N, C)` with respect to :meth:`moved`, summed over the events by
        :func:`sum_ignoring_padding` (events of zero gradient appended to a cluster do not change it,
        bit for bit): the backward pass of :meth:`moved`, for gradients chained by hand."""
        # A gradient of the displacement alone (C = 2) leaves out the maps of the steps.
        maps = self.maps[..., : grad_moved.shape[-1]]
        return _LinearMap.params_gradient(maps, grad_moved, (*grad_moved.shape[:-2], maps.shape[0]))


def area_from(moved: Tensor) -> Tensor:
    """The area element :math:`(..., N)` from :meth:`LinearWarp.moved` with the area element."""
    dx, dy = moved[..., 2:4], moved[..., 4:6]
    return (1 - dx[..., 0]) * (1 - dy[..., 1]) - dx[..., 1] * dy[..., 0]


def area_gradient(moved: Tensor) -> Tensor:
    """The derivative of :func:`area_from` in the step channels (2–5) of ``moved``, :math:`(..., N, 4)`
    (the displacement's channels do not change the area)."""
    dx, dy = moved[..., 2:4], moved[..., 4:6]
    return torch.stack([dy[..., 1] - 1, -dy[..., 0], -dx[..., 1], dx[..., 0] - 1], dim=-1)


def _apply(operator: Tensor, params: Tensor) -> Tensor:
    """Per-event ``operator @ params``: :math:`(P, ..., N, 2)`, :math:`(..., P)` -> :math:`(..., N, 2)`."""
    if params.ndim == 0 or params.shape[-1] != operator.shape[0]:
        raise ShapeError(f"params must be (..., {operator.shape[0]}), got {tuple(params.shape)}")
    if torch.is_grad_enabled() and (operator.requires_grad or params.requires_grad):
        return _LinearMap.apply(operator, params)
    # Nothing to differentiate (the fits' evaluations, hundreds per window): the product alone, without
    # an autograd.Function's call.
    return _product(operator, params)


def _product(operator: Tensor, params: Tensor) -> Tensor:
    # A sum over the few parameters of contiguous slices: 3x faster than matmul/einsum, which run one
    # tiny product per event or per cluster.
    product = operator[0] * params[..., 0, None, None]
    for index in range(1, operator.shape[0]):
        product = torch.addcmul(product, operator[index], params[..., index, None, None])
    return product


class _LinearMap(torch.autograd.Function):
    """:func:`_apply` with a backward pass that sums each parameter's gradient over the events by
    :func:`sum_ignoring_padding`: the gradient of a cluster padded with zero-weight events (to the
    largest cluster of a batch) is then the same, bit for bit, as without the padding, and a window's
    fits in a batch take exactly the steps they take alone (autograd's sums round differently for
    different lengths, and the fits' L-BFGS steps amplify that)."""

    @staticmethod
    def forward(ctx, operator: Tensor, params: Tensor) -> Tensor:
        ctx.save_for_backward(operator, params)
        return _product(operator, params)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:
        operator, params = ctx.saved_tensors
        grad_operator = grad_params = None
        if ctx.needs_input_grad[0]:
            shape, lead = operator.shape, grad.shape[:-2]
            coefficients = params.movedim(-1, 0)
            coefficients = coefficients.view(
                shape[0], *[1] * (len(lead) - params.ndim + 1), *params.shape[:-1], 1, 1
            )
            grad_operator = (
                (grad * coefficients).sum_to_size(_broadcast_view(operator, lead).shape).view(shape)
            )
        if ctx.needs_input_grad[1]:
            grad_params = _LinearMap.params_gradient(operator, grad, params.shape)
        return grad_operator, grad_params

    @staticmethod
    def params_gradient(operator: Tensor, grad: Tensor, params_shape: torch.Size) -> Tensor:
        """The backward pass into the parameters ``params_shape`` :math:`(..., P)`."""
        lead = grad.shape[:-2]
        sums = sum_ignoring_padding((_broadcast_view(operator, lead) * grad).flatten(-2))
        own_lead = (operator.shape[0], *[1] * (len(lead) - len(params_shape) + 1), *params_shape[:-1])
        return sums.sum_to_size(own_lead).movedim(0, -1).reshape(params_shape)


def _broadcast_view(operator: Tensor, lead: torch.Size) -> Tensor:
    """``operator`` :math:`(P, ..., N, C)` viewed with all of the product's leading dimensions ``lead``."""
    shape = operator.shape
    return operator.view(shape[0], *[1] * (len(lead) - len(shape) + 3), *shape[1:])


def sum_ignoring_padding(values: Tensor) -> Tensor:
    """Sum over the last dimension that zeros appended to it do not change, bit for bit.

    Fixed blocks of :data:`_SUM_BLOCK` values from the start (the last one completed with zeros) are
    summed, then the block sums added in order (``cumsum``): appended zeros only complete the last block
    or add blocks of zeros, which add exact zeros. On CUDA the sums are alike up to rounding only.
    """
    length = values.shape[-1]
    if not length:
        return values.new_zeros(values.shape[:-1])
    blocks = nn.functional.pad(values, (0, -length % _SUM_BLOCK)).unflatten(-1, (-1, _SUM_BLOCK)).sum(dim=-1)
    # One block (images up to 256 pixels wide or high): its sum is the total, no cumsum needed.
    return blocks[..., 0] if blocks.shape[-1] == 1 else blocks.cumsum(dim=-1)[..., -1]


def warp_events(model: MotionModel, xy: Tensor, t: Tensor, params: Tensor) -> Tensor:
    r"""Warp events to the reference time with one or several motions: ``x' = x - t v(x; params)``.

    This is :meth:`MotionModel.warp` with broadcasting: ``xy`` may be shared by all models or hold each
    model's own (padded) events. It uses the models' linear-velocity protocol ``v(x) = J(x) params``.

    Args:
        model: the motion model.
        xy: event positions :math:`(..., N, 2)`.
        t: event times in seconds relative to the reference time, :math:`(..., N)`.
        params: model parameters :math:`(..., P)`; leading dimensions broadcast against those of ``xy``.

    Returns:
        Warped positions, :math:`(..., N, 2)` with the broadcast leading dimensions.

    Raises:
        ShapeError: if the shapes do not fit together.

    Examples:
        >>> from evseg_torch.motion import Translation
        >>> warp_events(Translation((8, 8)), torch.rand(20, 2), torch.rand(20), torch.rand(3, 2)).shape
        torch.Size([3, 20, 2])
    """
    check_points(xy, "xy")
    if t.shape != xy.shape[:-1]:
        raise ShapeError(f"t must have shape {tuple(xy.shape[:-1])} to match xy, got {tuple(t.shape)}")
    if params.ndim == 0 or params.shape[-1] != model.n_params:
        raise ShapeError(
            f"params must be (..., {model.n_params}) for the {model.name} model, got {tuple(params.shape)}"
        )
    jacobian = model.jacobian(xy)
    # A sum over the few parameters: broadcast matmul runs one tiny product per event and model.
    velocity = jacobian[..., 0] * params[..., None, 0, None]
    for index in range(1, model.n_params):
        velocity = torch.addcmul(velocity, jacobian[..., index], params[..., None, index, None])
    return xy - t[..., None] * velocity
