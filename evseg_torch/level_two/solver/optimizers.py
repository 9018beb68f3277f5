r"""Batched minimisers of many small independent problems: L-BFGS and Adam as plain array code.

Every cluster's motion is its own problem of 2–8 parameters, and one evaluation of all of them is one
batched pass (a splat of every cluster's events). The solvers keep each problem's state in rows of
arrays, :math:`(C, P)` parameters and :math:`(C, m, P)` L-BFGS history, and ask ``evaluate`` for the
loss and gradient of just the running rows. The problems run asynchronously: each round evaluates
every running problem once, at the trial point of its own line search, whatever its iteration, so a
call costs as many batched evaluations as its slowest problem needs alone. No threads, no queues.

The state is tiny, so it lives in NumPy arrays (of the start's dtype) on the CPU whatever the device
of the evaluations: on arrays of a few dozen numbers, each torch operation costs several NumPy ones (the
bookkeeping of one L-BFGS round: 665 µs as torch code, 202 µs in NumPy). Only the trial points go to
the device, in the dtype of the start, and only the losses and gradients come back. Where Numba (the
optional ``fast`` extra) is installed, L-BFGS's bookkeeping between two evaluations runs as one compiled
call (:mod:`~evseg_torch.kernels.solver`), the same rounds step by step.

Each row follows the path it follows alone: its updates are elementwise or reduce over its own
parameters only, so a problem's result does not depend on the other problems, bit for bit on one
machine (as long as ``evaluate``'s rows do not; tested).

L-BFGS follows torch's :class:`~torch.optim.LBFGS` (two-loop recursion, initial Hessian
:math:`s^\top y / y^\top y`, a first step of ``lr * min(1, 1 / |g|_1)``, curvature pairs kept only
when :math:`s^\top y > 10^{-10}`, the same stopping tests and budgets), except for its line search
(:class:`_Search`), a simpler vectorised one than torch's strong-Wolfe search with cubic interpolation:
a deviation from torch's solver and from EMSGC's.

Its quality against torch's L-BFGS, and the variants measured:
``docs/notes/2026-12-03-solver-and-fit-evaluations.md``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from evseg_torch.backend import kernel

__all__ = [
    "ARMIJO",
    "BACK",
    "CURVATURE",
    "GROW",
    "MAX_TRIALS",
    "SHRINK",
    "TINY_STEP",
    "WOLFE",
    "adam",
    "lbfgs",
]

Evaluate = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
"""``evaluate(rows, x)``: the losses :math:`(R,)` and gradients :math:`(R, P)` of problems ``rows``
(int64 :math:`(R,)`, ascending) at their values ``x`` :math:`(R, P)`."""

ARMIJO = 1e-4  # sufficient decrease: f(x + t d) <= f(x) + c t g'd (torch's c1)
WOLFE = 0.9  # curvature: a step is long enough once g(x + t d)'d >= c g'd (torch's c2)
GROW = (2.0, 10.0)  # a longer step, as multiples of the last (torch extrapolates up to 10 times)
SHRINK = (0.1, 0.5)  # a rejected step's successor, as fractions of it
BACK = 0.9  # a step past the minimum is followed by one of at most this fraction of it
TINY_STEP = 1e-9  # a line search gives up on steps shorter than this in every coordinate
CURVATURE = 1e-10  # torch's threshold on s'y for keeping a curvature pair
MAX_TRIALS = 25  # evaluations per line search (torch's max_ls)


def _largest(a: np.ndarray) -> np.ndarray:
    return np.abs(a).max(axis=-1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products over the last dimension."""
    return (a * b).sum(axis=-1)


class _Evaluations:
    """``evaluate`` of NumPy rows and points (in the dtype of ``start``): the points go to its device,
    the losses and gradients come back as arrays of its dtype."""

    def __init__(self, evaluate: Evaluate, start: Tensor) -> None:
        self.evaluate, self.device, self.dtype = evaluate, start.device, start.dtype

    def __call__(self, rows: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        loss, grad = self.evaluate(
            torch.as_tensor(rows, device=self.device),
            torch.as_tensor(x, device=self.device),
        )
        return (value.detach().to(self.dtype).cpu().numpy() for value in (loss, grad))


def lbfgs(
    evaluate: Evaluate,
    start: Tensor,
    *,
    max_iter: int,
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
        The final values :math:`(C, P)`, on the device and in the dtype of ``start``.
    """
    run = kernel("solver.lbfgs") or _lbfgs
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        found = run(_Evaluations(evaluate, start), _as_array(start), max_iter, lr, tol)
    return torch.as_tensor(found, device=start.device)


def _lbfgs(evaluate: _Evaluations, x: np.ndarray, max_iter: int, lr: float, tol: float) -> np.ndarray:
    max_eval = max_iter * 5 // 4
    loss, grad = evaluate(np.arange(len(x)), x)
    evals = np.ones(len(x), dtype=np.int64)
    iterations = np.zeros_like(evals)
    history = _History(x, max_iter)
    # The first direction is the steepest descent, its first step at most lr in the l1 norm (torch's).
    direction = -grad
    slope = _dot(grad, direction)
    step = lr * np.minimum(1.0 / np.abs(grad).sum(axis=1), 1.0)
    running = (_largest(grad) > tol) & (slope <= -tol)
    search = _Search(loss, grad)
    trials = np.zeros_like(evals)  # of the current line search
    while running.any():
        rows = np.flatnonzero(running)
        trial = evaluate(rows, x[rows] + step[rows, None] * direction[rows])
        evals[rows] += 1
        trials += running
        step, searching = search.update(
            running, rows, trial, loss, slope, direction, step, trials < MAX_TRIALS
        )
        accept = running & ~searching & search.found
        taken = search.step[:, None] * direction
        history.push(accept, taken, search.grad - grad)
        previous = loss
        x = np.where(accept[:, None], x + taken, x)
        loss = np.where(accept, search.loss, loss)
        grad = np.where(accept[:, None], search.grad, grad)
        iterations += accept
        going = (
            accept
            & (iterations < max_iter)
            & (evals < max_eval)
            & (_largest(grad) > tol)
            & (_largest(taken) > tol)
            & (np.abs(loss - previous) >= tol)
        )
        running = searching
        if going.any():
            new_direction = history.direction(grad)
            new_slope = _dot(grad, new_direction)
            # Torch stops when the direction is not one of descent beyond the tolerance.
            going &= new_slope <= -tol
            direction = np.where(going[:, None], new_direction, direction)
            slope = np.where(going, new_slope, slope)
            step = np.where(going, lr, step)
            search.found &= ~going
            trials = np.where(going, 0, trials)
            running = running | going
    return x


class _History:
    """Each row's L-BFGS curvature pairs, oldest first: steps and gradient changes :math:`(C, m, P)`."""

    def __init__(self, x: np.ndarray, size: int) -> None:
        self.steps = np.zeros((x.shape[0], size, x.shape[1]), dtype=x.dtype)
        self.changes = np.zeros_like(self.steps)
        self.inverse_curvature = np.zeros((x.shape[0], size), dtype=x.dtype)
        self.pairs = np.zeros(x.shape[0], dtype=np.int64)

    def push(self, rows: np.ndarray, s: np.ndarray, y: np.ndarray) -> None:
        """Append the pair ``(s, y)`` of each row of the mask ``rows`` whose curvature is positive."""
        curvature = _dot(s, y)
        index = np.flatnonzero(rows & (curvature > CURVATURE))
        if len(index):
            slot = self.pairs[index]
            self.steps[index, slot] = s[index]
            self.changes[index, slot] = y[index]
            self.inverse_curvature[index, slot] = 1.0 / curvature[index]
            self.pairs[index] = slot + 1

    def direction(self, g: np.ndarray) -> np.ndarray:
        """The L-BFGS direction :math:`-H g` of every row by the two-loop recursion."""
        pairs, steps, changes, inverse = self.pairs, self.steps, self.changes, self.inverse_curvature
        used = int(pairs.max())
        q = -g
        alphas = []
        for slot in reversed(range(used)):
            alpha = np.where(slot < pairs, inverse[:, slot] * _dot(steps[:, slot], q), 0.0)
            q = q - alpha[:, None] * changes[:, slot]
            alphas.append(alpha)
        if not used:
            return q
        newest = np.maximum(pairs - 1, 0)
        rows = np.arange(len(pairs))
        s, y = steps[rows, newest], changes[rows, newest]
        # Rows without pairs have s = y = 0 and keep the steepest-descent direction.
        gamma = np.where(pairs > 0, _dot(s, y) / np.maximum(_dot(y, y), np.finfo(g.dtype).tiny), 1.0)
        r = q * gamma[:, None]
        for slot, alpha in zip(range(used), reversed(alphas), strict=True):
            beta = inverse[:, slot] * _dot(changes[:, slot], r)
            r = r + np.where(slot < pairs, alpha - beta, 0.0)[:, None] * steps[:, slot]
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
    it). A search also ends after ``MAX_TRIALS`` trials or when its step is below ``TINY_STEP`` in
    every coordinate.
    """

    def __init__(self, loss: np.ndarray, grad: np.ndarray) -> None:
        self.found = np.zeros(loss.shape, dtype=bool)
        self.loss, self.grad, self.step = loss.copy(), grad.copy(), np.zeros_like(loss)

    def update(
        self,
        active: np.ndarray,
        rows: np.ndarray,
        trial: tuple[np.ndarray, np.ndarray],
        loss: np.ndarray,
        slope: np.ndarray,
        direction: np.ndarray,
        step: np.ndarray,
        budget: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Take the trials ``(loss, grad)`` of ``rows`` (the mask ``active``); returns every row's next
        step and which rows search on."""
        # Full-size copies; the other rows' zeros are masked out of every update.
        trial_loss, trial_grad = np.zeros_like(loss), np.zeros_like(self.grad)
        trial_loss[rows], trial_grad[rows] = trial
        trial_slope = _dot(trial_grad, direction)
        sufficient = trial_loss <= loss + ARMIJO * step * slope
        better = active & sufficient & ~(self.found & (trial_loss > self.loss))
        self.loss = np.where(better, trial_loss, self.loss)
        self.grad = np.where(better[:, None], trial_grad, self.grad)
        self.step = np.where(better, step, self.step)
        self.found = self.found | better
        longer = better & (trial_slope < WOLFE * slope)
        # Past the minimum and rising steeply there: the minimum lies between 0 and the step.
        back = better & (trial_slope > -WOLFE * slope)
        shorter = active & ~better & ~self.found
        # The secant's zero of the directional derivative: beyond the step where the slope flattens
        # (where it steepens, the longest step), within it where the slope turned positive.
        secant = step * slope / (slope - trial_slope)
        grown = np.where(trial_slope > slope, secant, GROW[1] * step)
        grown = np.minimum(np.maximum(grown, GROW[0] * step), GROW[1] * step)
        inside = np.minimum(np.maximum(secant, SHRINK[0] * step), BACK * step)
        curve = trial_loss - loss - slope * step
        shrunk = -slope * step * step / (2 * curve)
        shrunk = np.where(np.isfinite(shrunk) & (curve > 0), shrunk, SHRINK[1] * step)
        shrunk = np.minimum(np.maximum(shrunk, SHRINK[0] * step), SHRINK[1] * step)
        next_step = np.where(longer, grown, np.where(back, inside, shrunk))
        long_enough = _largest(next_step[:, None] * direction) > TINY_STEP
        searching = (longer | ((back | shorter) & long_enough)) & budget
        return np.where(searching, next_step, step), searching


def adam(
    evaluate: Evaluate,
    start: Tensor,
    *,
    max_iter: int,
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
        The final values :math:`(C, P)`, on the device and in the dtype of ``start``.
    """
    evaluations = _Evaluations(evaluate, start)
    x = _as_array(start)
    first, second = np.zeros_like(x), np.zeros_like(x)
    previous = np.full(len(x), np.nan, dtype=x.dtype)
    running = np.ones(len(x), dtype=bool)
    for step in range(1, max_iter + 1):
        rows = np.flatnonzero(running)
        if not len(rows):
            break
        loss, grad = evaluations(rows, x[rows])
        first[rows] = betas[0] * first[rows] + (1 - betas[0]) * grad
        second[rows] = betas[1] * second[rows] + (1 - betas[1]) * grad * grad
        denominator = np.sqrt(second[rows]) / (1 - betas[1] ** step) ** 0.5 + eps
        x[rows] = x[rows] - lr / (1 - betas[0] ** step) * first[rows] / denominator
        with np.errstate(invalid="ignore"):
            running[rows] = ~(np.abs(previous[rows] - loss) < tol)
        previous[rows] = loss
    return torch.as_tensor(x, device=start.device)


def _as_array(start: Tensor) -> np.ndarray:
    """A NumPy copy of the starting values, in their dtype."""
    return start.detach().cpu().numpy().copy()
