r"""Batched minimisers of many small independent problems: L-BFGS and Adam as plain tensor code.

Every cluster's motion is its own problem of 2–8 parameters, and one evaluation of all of them is one
batched pass (a splat of every cluster's events). The solvers keep each problem's state in rows of
tensors, :math:`(C, P)` parameters and :math:`(C, m, P)` L-BFGS history, and ask ``evaluate`` for the
loss and gradient of just the running rows. The problems run asynchronously: each round evaluates
every running problem once, at the trial point of its own line search, whatever its iteration, so a
call costs as many batched evaluations as its slowest problem needs alone. No threads, no queues.

Each row follows the path it follows alone: its updates are elementwise or reduce over its own
parameters only, so a problem's result does not depend on the other problems, bit for bit on one
machine (as long as ``evaluate``'s rows do not; tested).

L-BFGS follows torch's :class:`~torch.optim.LBFGS` (two-loop recursion, initial Hessian
:math:`s^\top y / y^\top y`, a first step of ``lr * min(1, 1 / |g|_1)``, curvature pairs kept only
when :math:`s^\top y > 10^{-10}`, the same stopping tests and budgets), except for its line search
(:class:`_Search`), a simpler vectorised one than torch's strong-Wolfe search with cubic interpolation:
a deviation from torch's solver and from EMSGC's.

Its quality against torch's L-BFGS, and the variants measured, are in ``docs/speed.md``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

Evaluate = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
"""``evaluate(rows, x)``: the losses :math:`(R,)` and gradients :math:`(R, P)` of problems ``rows``
(int64 :math:`(R,)`, ascending) at their values ``x`` :math:`(R, P)`."""

_ARMIJO = 1e-4  # sufficient decrease: f(x + t d) <= f(x) + c t g'd (torch's c1)
_WOLFE = 0.9  # curvature: a step is long enough once g(x + t d)'d >= c g'd (torch's c2)
_GROW = (2.0, 10.0)  # a longer step, as multiples of the last (torch extrapolates up to 10 times)
_SHRINK = (0.1, 0.5)  # a rejected step's successor, as fractions of it
_BACK = 0.9  # a step past the minimum is followed by one of at most this fraction of it
_TINY_STEP = 1e-9  # a line search gives up on steps shorter than this in every coordinate
_CURVATURE = 1e-10  # torch's threshold on s'y for keeping a curvature pair
_MAX_TRIALS = 25  # evaluations per line search (torch's max_ls)


def _largest(a: Tensor) -> Tensor:
    return a.abs().amax(dim=-1)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot products over the last dimension."""
    return (a * b).sum(dim=-1)


def lbfgs(
    evaluate: Evaluate,
    start: Tensor,
    *,
    max_iter: int = 20,
    lr: float = 1.0,
    tol: float = 1e-6,
) -> Tensor:
    """Minimise C independent problems by L-BFGS (module docstring).

    A problem stops when its largest gradient component or step is at most ``tol``, its loss changes
    by less than ``tol``, it has taken ``max_iter`` iterations, its evaluations reach
    ``max_iter * 5 // 4`` (checked between iterations, as torch does: a line search begun may take up
    to 25 trials), or its line search found no sufficient decrease (it keeps its last accepted value).

    Args:
        evaluate: see :data:`Evaluate`.
        start: starting values :math:`(C, P)`.
        max_iter: iterations per problem.
        lr: the step tried first along each search direction.
        tol: tolerance on gradients, steps and changes of the loss.

    Returns:
        The final values :math:`(C, P)`.
    """
    max_eval = max_iter * 5 // 4
    x = start.detach().clone()
    loss, grad = (value.detach() for value in evaluate(torch.arange(len(x), device=x.device), x))
    evals = torch.ones(len(x), dtype=torch.long, device=x.device)
    iterations = torch.zeros_like(evals)
    history = _History(x, max_iter)
    # The first direction is the steepest descent, its first step at most lr in the l1 norm (torch's).
    direction = -grad
    slope = _dot(grad, direction)
    step = lr * torch.clamp(1.0 / grad.abs().sum(dim=1), max=1.0)
    running = (_largest(grad) > tol) & (slope <= -tol)
    search = _Search(loss, grad)
    trials = torch.zeros_like(evals)  # of the current line search
    while running.any():
        rows = running.nonzero()[:, 0]
        trial = evaluate(rows, x[rows] + step[rows, None] * direction[rows])
        evals[rows] += 1
        trials += running.long()
        step, searching = search.update(
            running, rows, trial, loss, slope, direction, step, trials < _MAX_TRIALS
        )
        accept = running & ~searching & search.found
        taken = search.step[:, None] * direction
        history.push(accept, taken, search.grad - grad)
        previous = loss
        x = torch.where(accept[:, None], x + taken, x)
        loss = torch.where(accept, search.loss, loss)
        grad = torch.where(accept[:, None], search.grad, grad)
        iterations += accept.long()
        going = (
            accept
            & (iterations < max_iter)
            & (evals < max_eval)
            & (_largest(grad) > tol)
            & (_largest(taken) > tol)
            & ((loss - previous).abs() >= tol)
        )
        running = searching
        if going.any():
            new_direction = history.direction(grad)
            new_slope = _dot(grad, new_direction)
            # Torch stops when the direction is not one of descent beyond the tolerance.
            going &= new_slope <= -tol
            direction = torch.where(going[:, None], new_direction, direction)
            slope = torch.where(going, new_slope, slope)
            step = torch.where(going, lr, step)
            search.found &= ~going
            trials = torch.where(going, 0, trials)
            running = running | going
    return x


class _History:
    """Each row's L-BFGS curvature pairs, oldest first: steps and gradient changes :math:`(C, m, P)`."""

    def __init__(self, x: Tensor, size: int) -> None:
        self.steps = x.new_zeros(x.shape[0], size, x.shape[1])
        self.changes = torch.zeros_like(self.steps)
        self.inverse_curvature = x.new_zeros(x.shape[0], size)
        self.pairs = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)

    def push(self, rows: Tensor, s: Tensor, y: Tensor) -> None:
        """Append the pair ``(s, y)`` of each row of the mask ``rows`` whose curvature is positive."""
        curvature = _dot(s, y)
        index = (rows & (curvature > _CURVATURE)).nonzero()[:, 0]
        if len(index):
            slot = self.pairs[index]
            self.steps[index, slot] = s[index]
            self.changes[index, slot] = y[index]
            self.inverse_curvature[index, slot] = 1.0 / curvature[index]
            self.pairs[index] = slot + 1

    def direction(self, g: Tensor) -> Tensor:
        """The L-BFGS direction :math:`-H g` of every row by the two-loop recursion."""
        pairs, steps, changes, inverse = self.pairs, self.steps, self.changes, self.inverse_curvature
        used = int(pairs.max())
        q = -g
        alphas = []
        for slot in reversed(range(used)):
            alpha = torch.where(slot < pairs, inverse[:, slot] * _dot(steps[:, slot], q), 0.0)
            q = q - alpha[:, None] * changes[:, slot]
            alphas.append(alpha)
        if not used:
            return q
        newest = (pairs - 1).clamp(min=0)[:, None, None].expand(-1, 1, g.shape[1])
        s, y = steps.gather(1, newest)[:, 0], changes.gather(1, newest)[:, 0]
        # Rows without pairs have s = y = 0 and keep the steepest-descent direction.
        gamma = torch.where(pairs > 0, _dot(s, y) / _dot(y, y).clamp_min(torch.finfo(g.dtype).tiny), 1.0)
        r = q * gamma[:, None]
        for slot, alpha in zip(range(used), reversed(alphas), strict=True):
            beta = inverse[:, slot] * _dot(changes[:, slot], r)
            r = r + torch.where(slot < pairs, alpha - beta, 0.0)[:, None] * steps[:, slot]
        return r


class _Search:
    """Every row's line search: whether it ``found`` a step yet, and the best one's loss and gradient.

    A trial step with sufficient decrease (Armijo) that is no worse than the row's best becomes its
    best; the search then ends if the directional derivative there meets the curvature test or has
    turned positive, and otherwise tries a longer step (the secant's zero of the directional
    derivative, 2–10 times the step). A trial without sufficient decrease ends the search at the best
    step if there is one, and otherwise shrinks the step (the minimum of the quadratic through f(0),
    f'(0) and f(t), 10–50 % of it). A best step past the minimum, where the directional derivative
    has turned steeply positive, is followed by the secant's zero between 0 and it (at most 90 % of
    it). A search also ends after ``_MAX_TRIALS`` trials or when its step is below ``_TINY_STEP`` in
    every coordinate.
    """

    def __init__(self, loss: Tensor, grad: Tensor) -> None:
        self.found = torch.zeros_like(loss, dtype=torch.bool)
        self.loss, self.grad, self.step = loss.clone(), grad.clone(), torch.zeros_like(loss)

    def update(
        self,
        active: Tensor,
        rows: Tensor,
        trial: tuple[Tensor, Tensor],
        loss: Tensor,
        slope: Tensor,
        direction: Tensor,
        step: Tensor,
        budget: Tensor,
    ) -> tuple[Tensor, Tensor]:
        """Take the trials ``(loss, grad)`` of ``rows`` (the mask ``active``); returns every row's next
        step and which rows search on."""
        # Full-size copies; the other rows' zeros are masked out of every update.
        trial_loss = torch.zeros_like(loss).index_copy_(0, rows, trial[0].detach())
        trial_grad = torch.zeros_like(self.grad).index_copy_(0, rows, trial[1].detach())
        trial_slope = _dot(trial_grad, direction)
        sufficient = trial_loss <= loss + _ARMIJO * step * slope
        better = active & sufficient & ~(self.found & (trial_loss > self.loss))
        self.loss = torch.where(better, trial_loss, self.loss)
        self.grad = torch.where(better[:, None], trial_grad, self.grad)
        self.step = torch.where(better, step, self.step)
        self.found = self.found | better
        longer = better & (trial_slope < _WOLFE * slope)
        # Past the minimum and rising steeply there: the minimum lies between 0 and the step.
        back = better & (trial_slope > -_WOLFE * slope)
        shorter = active & ~better & ~self.found
        # The secant's zero of the directional derivative: beyond the step where the slope flattens
        # (where it steepens, the longest step), within it where the slope turned positive.
        secant = step * slope / (slope - trial_slope)
        grown = torch.where(trial_slope > slope, secant, _GROW[1] * step)
        grown = torch.minimum(torch.maximum(grown, _GROW[0] * step), _GROW[1] * step)
        inside = torch.minimum(torch.maximum(secant, _SHRINK[0] * step), _BACK * step)
        curve = trial_loss - loss - slope * step
        shrunk = -slope * step * step / (2 * curve)
        shrunk = torch.where(torch.isfinite(shrunk) & (curve > 0), shrunk, _SHRINK[1] * step)
        shrunk = torch.minimum(torch.maximum(shrunk, _SHRINK[0] * step), _SHRINK[1] * step)
        next_step = torch.where(longer, grown, torch.where(back, inside, shrunk))
        long_enough = _largest(next_step[:, None] * direction) > _TINY_STEP
        searching = (longer | ((back | shorter) & long_enough)) & budget
        return torch.where(searching, next_step, step), searching


def adam(
    evaluate: Evaluate,
    start: Tensor,
    *,
    max_iter: int = 20,
    lr: float = 0.1,
    tol: float = 1e-6,
    betas: tuple[float, float] = (0.9, 0.999),
    eps: float = 1e-8,
) -> Tensor:
    """Minimise C independent problems by Adam (torch's update), ``max_iter`` steps each.

    A problem stops once its loss changes by less than ``tol`` between two steps.

    Args:
        evaluate: see :data:`Evaluate`.
        start: starting values :math:`(C, P)`.
        max_iter: steps per problem.
        lr, betas, eps: Adam's settings.
        tol: tolerance on changes of the loss.

    Returns:
        The final values :math:`(C, P)`.
    """
    x = start.detach().clone()
    first, second = torch.zeros_like(x), torch.zeros_like(x)
    previous = torch.full_like(x[:, 0], float("nan"))
    running = torch.ones(len(x), dtype=torch.bool, device=x.device)
    for step in range(1, max_iter + 1):
        rows = running.nonzero()[:, 0]
        if not len(rows):
            break
        loss, grad = (value.detach() for value in evaluate(rows, x[rows]))
        first[rows] = betas[0] * first[rows] + (1 - betas[0]) * grad
        second[rows] = betas[1] * second[rows] + (1 - betas[1]) * grad * grad
        denominator = second[rows].sqrt() / (1 - betas[1] ** step) ** 0.5 + eps
        x[rows] = x[rows] - lr / (1 - betas[0] ** step) * first[rows] / denominator
        running[rows] = ~((previous[rows] - loss).abs() < tol)
        previous[rows] = loss
    return x
