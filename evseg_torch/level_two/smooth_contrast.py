r"""Contrast of a Gaussian splat, with its gradient and Hessian in the motion parameters, by hand.

The fits' usual image (:mod:`~evseg_torch.level_two.iwe_variance`) votes bilinearly and then blurs: a
piecewise linear function of the warped positions, whose second derivative in the parameters is the
concave ``-2 JᵀJ`` of the variance plus nothing from the kinks, where the curvature of a maximum lives.
A Newton step needs that curvature, so :func:`splat_contrast_terms` splats each event as a Gaussian of
``sigma`` pixels (7 × 7 taps at ``sigma = 1``), a smooth image of the parameters:

.. math::

    I_p(\theta) = \sum_k v_k\, g(p - x'_k(\theta)), \qquad
    g(u) = e^{-|u|^2 / 2\sigma^2}, \qquad
    L(\theta) = -\frac{1}{|\Omega|} \sum_{p \in \Omega} (I_p - \bar I)^2 .

With ``x'_k = x_k - A_k \theta`` (the linear warp, :class:`~evseg_torch.level_two.linear_warp.LinearWarp`)
and ``e_p = -2 (I_p - \bar I) / |\Omega|`` (the loss's derivative in the image):

* gradient: :math:`\nabla L = -\sum_k A_k^\top \sum_t e_{p_t}\, v_k\, g\, u_t / \sigma^2` over each event's
  taps :math:`t` (``u = p - x'``), plus the collapse guard's votes ``v = w a^\gamma`` as in the fits' loss;
* Hessian: :math:`-\frac{2}{|\Omega|} \sum_p D_p D_p^\top` with :math:`D_p = \partial I_p / \partial\theta`
  (the mean's part subtracted), plus :math:`\sum_k v_k A_k^\top M_k A_k` with
  :math:`M_k = \sum_t e_{p_t}\, g\, (u u^\top / \sigma^4 - I / \sigma^2)`, the splat's own curvature.
  The votes count as constants here (the guard's second derivatives are left out: the Hessian of a
  Newton step, not of the loss).

Gaussian taps beyond ``truncate`` sigmas are dropped, as the blur's kernel is truncated. Images live
in a canvas of ``size`` with an optional per-cluster pixel ``mask`` (crops), like the fits' loss.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evseg_torch.level_two.linear_warp import LinearWarp, area_from, area_gradient, sum_ignoring_padding

_MIN_AREA = 1e-6  # as the fits' loss: folded warps keep a tiny weight and a finite gradient


def splat_contrast_terms(
    warp: LinearWarp,
    params: Tensor,
    weights: Tensor,
    size: tuple[int, int],
    sigma: float,
    collapse_weight: float,
    mask: Tensor | None = None,
    divisor: Tensor | None = None,
    order: int = 2,
    truncate: float = 3.0,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    r"""Negative variance of each cluster's Gaussian splat, and its gradient and Hessian (module docstring).

    Args:
        warp: the clusters' warps, events :math:`(R, n)`.
        params: :math:`(R, P)`.
        weights: :math:`(R, n)`; zero on padding.
        size: the canvas ``(H, W)``.
        sigma: the Gaussian's standard deviation in pixels, > 0.
        collapse_weight: exponent γ of the event-collapse guard's area votes; 0 switches it off.
        mask: optional bool :math:`(R, H, W)`, each cluster's pixels of the canvas.
        divisor: optional :math:`(R,)`; every term is divided by it.
        order: 0 for the losses alone, 1 with their gradients, 2 with their Hessians too.
        truncate: taps reach ``ceil(truncate * sigma)`` pixels each way.

    Returns:
        ``(loss, grad, hess)``: :math:`(R,)`, :math:`(R, P)` or ``None``, :math:`(R, P, P)` or ``None``.
    """
    height, width = size
    radius = math.ceil(truncate * sigma)
    reach = torch.arange(-radius, radius + 1, dtype=params.dtype, device=params.device)
    n_rows = params.shape[0]
    moved = warp.moved(params)  # (R, n, C)
    votes = weights
    if collapse_weight > 0:
        area = area_from(moved)
        clamped = area.clamp_min(_MIN_AREA)
        powered = clamped**collapse_weight
        votes = powered * weights
    xy = warp.warped_from(moved)  # (R, n, 2)
    corner = xy.floor()
    # Taps (R, n, T): pixel offsets dx (columns) and dy (rows) around each event's floored position.
    dx = (corner[..., 0, None] + reach) - xy[..., 0, None]  # (R, n, S)
    dy = (corner[..., 1, None] + reach) - xy[..., 1, None]
    gx, gy = torch.exp(-0.5 * (dx / sigma) ** 2), torch.exp(-0.5 * (dy / sigma) ** 2)
    col = corner[..., 0, None].long() + torch.arange(-radius, radius + 1, device=params.device)
    row = corner[..., 1, None].long() + torch.arange(-radius, radius + 1, device=params.device)
    col_in, row_in = (col >= 0) & (col < width), (row >= 0) & (row < height)
    inside = (row_in[..., :, None] & col_in[..., None, :]).flatten(-2)  # (R, n, T), row-major taps
    pixel = (row.clamp(0, height - 1)[..., :, None] * width + col.clamp(0, width - 1)[..., None, :]).flatten(
        -2
    )
    pixel = pixel + (torch.arange(n_rows, device=params.device) * height * width)[:, None, None]
    kernel = (gy[..., :, None] * gx[..., None, :]).flatten(-2) * inside  # (R, n, T)
    flat_pixel = pixel.flatten()
    image = params.new_zeros(n_rows * height * width).index_add_(
        0, flat_pixel, (kernel * votes[..., None]).flatten()
    )
    image = image.view(n_rows, height, width)
    if mask is not None:
        image = image * mask
        count = mask.sum(dim=(-2, -1)).to(params.dtype)
    else:
        count = params.new_full((n_rows,), float(height * width))
    mean = _image_sum(image) / count
    deviation = image - mean[:, None, None]
    if mask is not None:
        deviation = deviation * mask
    scale = torch.ones_like(count) if divisor is None else 1.0 / divisor
    loss = -_image_sum(deviation.square()) / count * scale
    if order == 0:
        return loss, None, None

    # e_p, the loss's derivative in the image, read at every tap.
    slope = (-2.0 * scale / count)[:, None, None] * deviation
    at_taps = slope.flatten().index_select(0, flat_pixel).view_as(kernel) * kernel  # e g, (R, n, T)
    ux = dx[..., None, :].expand(*dx.shape[:-1], dy.shape[-1], dx.shape[-1]).flatten(-2) / sigma**2
    uy = dy[..., :, None].expand(*dy.shape[:-1], dy.shape[-1], dx.shape[-1]).flatten(-2) / sigma**2
    # dL/dx' = sum_t e g u / sigma^2 times the vote; x' = x - moved, so dL/dmoved is its negative.
    pull = torch.stack([(at_taps * ux).sum(-1), (at_taps * uy).sum(-1)], dim=-1)  # (R, n, 2)
    grad_moved = -pull * votes[..., None]
    if collapse_weight > 0:
        grad_votes = at_taps.sum(-1)  # dL/dv
        guard = torch.where(area >= _MIN_AREA, collapse_weight * powered / clamped, 0.0) * weights
        grad_moved = torch.cat([grad_moved, (grad_votes * guard)[..., None] * area_gradient(moved)], dim=-1)
    grad = warp.params_gradient(grad_moved)
    if order == 1:
        return loss, grad, None

    # The displacement's maps A (R, n, 2, P): x' = x - A theta.
    maps = warp.maps[..., :2].movedim(0, -1)  # (R, n, 2, P)
    # D_p = dI_p/dtheta = sum over taps of v g (u / sigma^2)' (-A) + g dv: one (P,) vector per tap, scattered.
    per_tap = -(ux[..., None] * maps[..., 0, None, :] + uy[..., None] * maps[..., 1, None, :])  # (R, n, T, P)
    per_tap = per_tap * (kernel * votes[..., None])[..., None]
    n_params = maps.shape[-1]
    if collapse_weight > 0:
        # The votes v = w a^gamma of the area element a, a quadratic of theta through the steps' maps.
        steps = warp.maps[..., 2:6].movedim(0, -1)  # (R, n, 4, P): the channels a is made of
        area_slope = (area_gradient(moved)[..., None] * steps).sum(-2)  # da/dtheta, (R, n, P)
        dv = guard[..., None] * area_slope
        per_tap = per_tap + kernel[..., None] * dv[..., None, :]
    jacobian = params.new_zeros(n_rows * height * width, n_params)
    jacobian = jacobian.index_add_(0, flat_pixel, per_tap.flatten(0, 2)).view(n_rows, height, width, n_params)
    if mask is not None:
        jacobian = jacobian * mask[..., None]
    jacobian = jacobian.movedim(-1, 1)  # (R, P, H, W)
    # Sums over the canvas and over the events that its padding (zeros) does not change, bit for bit, as
    # in the fits' loss: a cluster's terms are the same alone and beside larger ones.
    mean_jacobian = _image_sum(jacobian) / count[:, None]
    gauss_newton = _image_sum(jacobian[:, :, None] * jacobian[:, None, :]) - count[:, None, None] * (
        mean_jacobian[:, :, None] * mean_jacobian[:, None, :]
    )
    # M_k = sum_t e g (u u' / sigma^4 - I / sigma^2), symmetric 2 x 2 per event, times the vote.
    mxx = (at_taps * (ux * ux - 1.0 / sigma**2)).sum(-1) * votes
    myy = (at_taps * (uy * uy - 1.0 / sigma**2)).sum(-1) * votes
    mxy = (at_taps * ux * uy).sum(-1) * votes
    curvature = torch.stack([torch.stack([mxx, mxy], -1), torch.stack([mxy, myy], -1)], -2)  # (R, n, 2, 2)
    per_event = maps.transpose(-2, -1) @ (curvature @ maps)  # (R, n, P, P)
    if collapse_weight > 0:
        # The votes' own derivatives: sum_t e dg dv' (both ways) and (sum_t e g) d2v.
        tilt = -(pull[..., :, None] * maps).sum(-2)  # sum_t e dg/dtheta, (R, n, P)
        cross = tilt[..., :, None] * dv[..., None, :]
        # d2a: a = (1 - sx0)(1 - sy1) - sx1 sy0 with each step channel linear in theta.
        sx0, sx1, sy0, sy1 = steps.unbind(-2)
        bend = _sym(sx0, sy1) - _sym(sx1, sy0)
        outer = area_slope[..., :, None] * area_slope[..., None, :]
        curve = collapse_weight * (collapse_weight - 1.0) * powered / clamped**2
        d2v = (
            torch.where(area >= _MIN_AREA, 1.0, 0.0)[..., None, None]
            * weights[..., None, None]
            * (curve[..., None, None] * outer + (collapse_weight * powered / clamped)[..., None, None] * bend)
        )
        per_event = per_event + cross + cross.transpose(-2, -1) + grad_votes[..., None, None] * d2v
    splat_part = sum_ignoring_padding(per_event.movedim(1, -1))
    hess = (-2.0 * scale / count)[:, None, None] * gauss_newton + splat_part
    return loss, grad, hess


def _image_sum(values: Tensor) -> Tensor:
    """Sum over the last two dimensions (rows, then columns) that appended zeros do not change."""
    return sum_ignoring_padding(sum_ignoring_padding(values))


def _sym(a: Tensor, b: Tensor) -> Tensor:
    """``a b' + b a'`` of row vectors :math:`(..., P)`, :math:`(..., P, P)`."""
    outer = a[..., :, None] * b[..., None, :]
    return outer + outer.transpose(-2, -1)
