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

# Values per block of sum_ignoring_padding: long enough for torch's fast sums, short enough that the
# zeros completing the last block cost little.
_SUM_BLOCK = 256


class LinearWarp(NamedTuple):
    """The warp of fixed events as a linear map of the parameters (``v = J(x) params``): built once,
    it turns every evaluation of an optimiser into a few multiply-adds.

    ``operator`` is ``t J(x)`` and ``step_x``, ``step_y`` are ``t (J(x + e) - J(x))`` for one-pixel steps
    ``e`` (for the area element), all stored parameter-first, :math:`(P, ..., N, 2)`.
    """

    xy: Tensor
    operator: Tensor
    step_x: Tensor | None
    step_y: Tensor | None

    @classmethod
    def build(cls, model: MotionModel, events: EventBatch, with_area: bool = True) -> LinearWarp:
        check_points(events.xy, "events.xy")
        if events.t.shape != events.xy.shape[:-1]:
            raise ShapeError(
                f"events.t must have shape {tuple(events.xy.shape[:-1])} to match events.xy, "
                f"got {tuple(events.t.shape)}"
            )
        t = events.t[..., None, None]
        jacobian = model.jacobian(events.xy)
        operator = _parameter_first(t * jacobian)
        if not with_area:
            return cls(events.xy, operator, None, None)
        unit = torch.eye(2, dtype=events.xy.dtype, device=events.xy.device)
        step_x, step_y = (_parameter_first(t * (model.jacobian(events.xy + e) - jacobian)) for e in unit)
        return cls(events.xy, operator, step_x, step_y)

    def warped(self, params: Tensor) -> Tensor:
        return self.xy - _apply(self.operator, params)

    def rows(self, index: Tensor) -> LinearWarp:
        """The warp of some clusters of a gathered :math:`(K, N, 2)` warp: rows ``index``."""
        steps = (None if step is None else step[:, index] for step in (self.step_x, self.step_y))
        return LinearWarp(self.xy[index], self.operator[:, index], *steps)

    def area(self, params: Tensor) -> Tensor:
        dx, dy = _apply(self.step_x, params), _apply(self.step_y, params)
        return (1 - dx[..., 0]) * (1 - dy[..., 1]) - dx[..., 1] * dy[..., 0]


def _apply(operator: Tensor, params: Tensor) -> Tensor:
    """Per-event ``operator @ params``: :math:`(P, ..., N, 2)`, :math:`(..., P)` -> :math:`(..., N, 2)`."""
    if params.ndim == 0 or params.shape[-1] != operator.shape[0]:
        raise ShapeError(f"params must be (..., {operator.shape[0]}), got {tuple(params.shape)}")
    return _LinearMap.apply(operator, params)


class _LinearMap(torch.autograd.Function):
    """:func:`_apply` with a backward pass that sums each parameter's gradient over the events by
    :func:`sum_ignoring_padding`: the gradient of a cluster padded with zero-weight events (to the
    largest cluster of a batch) is then the same, bit for bit, as without the padding, and a window's
    fits in a batch take exactly the steps they take alone (autograd's sums round differently for
    different lengths, and the fits' L-BFGS steps amplify that)."""

    @staticmethod
    def forward(ctx, operator: Tensor, params: Tensor) -> Tensor:
        ctx.save_for_backward(operator, params)
        # A sum over the few parameters of contiguous slices: 3x faster than matmul/einsum, which run
        # one tiny product per event or per cluster.
        product = operator[0] * params[..., 0, None, None]
        for index in range(1, operator.shape[0]):
            product = torch.addcmul(product, operator[index], params[..., index, None, None])
        return product

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:
        operator, params = ctx.saved_tensors
        shape, n_params, lead = operator.shape, operator.shape[0], grad.shape[:-2]
        # Both inputs viewed with all of the product's leading dimensions, parameters first.
        operator = operator.view(n_params, *[1] * (len(lead) - len(shape) + 3), *shape[1:])
        coefficients = params.movedim(-1, 0)
        coefficients = coefficients.view(
            n_params, *[1] * (len(lead) - params.ndim + 1), *params.shape[:-1], 1, 1
        )
        grad_operator = grad_params = None
        if ctx.needs_input_grad[0]:
            grad_operator = (grad * coefficients).sum_to_size(operator.shape).view(shape)
        if ctx.needs_input_grad[1]:
            sums = sum_ignoring_padding((operator * grad).flatten(-2))
            grad_params = sums.sum_to_size(coefficients.shape[:-2]).movedim(0, -1).reshape(params.shape)
        return grad_operator, grad_params


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


def _parameter_first(operator: Tensor) -> Tensor:
    return operator.movedim(-1, 0).contiguous()
