"""The batched L-BFGS's bookkeeping as compiled loops over its rows (Numba).

:func:`~evseg_torch.level_two.solver.optimizers.lbfgs` keeps every problem's state in rows of NumPy
arrays and updates them with about a hundred array operations per round; on a few dozen numbers each,
their calls take the time. :func:`lbfgs` runs the same
rounds with the bookkeeping between two evaluations as one compiled call: each row's line search,
curvature pair, acceptance, stopping tests and two-loop recursion, written as the NumPy code's steps
in its order and dtype (constants in the dtype of the state, as NumPy casts Python scalars; sums of the
few parameters in order from zero, as NumPy adds them; IEEE division, NaN through ``minimum`` and
``maximum``), so its results equal the NumPy code's bit for bit on this machine (tested on the solvers'
problems). The evaluations are the caller's. :mod:`evseg_torch.backend` chooses it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evseg_torch.kernels.common import maximum
from evseg_torch.level_two.solver import optimizers as solver

_OPTIONS = {"cache": True, "error_model": "numpy"}  # IEEE results of x / 0, as NumPy's


def lbfgs(evaluate, x: np.ndarray, max_iter: int, lr: float, tol: float) -> np.ndarray:
    """:func:`~evseg_torch.level_two.solver.optimizers._lbfgs`: the same arguments, the same result."""
    dtype = x.dtype.type
    constants = np.array(
        [
            lr,
            tol,
            solver.ARMIJO,
            solver.WOLFE,
            *solver.GROW,
            *solver.SHRINK,
            solver.BACK,
            solver.TINY_STEP,
            solver.CURVATURE,
            np.finfo(x.dtype).tiny,
        ],
        dtype=dtype,
    )
    limits = np.array([max_iter, max_iter * 5 // 4, solver.MAX_TRIALS], dtype=np.int64)
    n_rows, n_params = x.shape
    loss, grad = evaluate(np.arange(n_rows), x)
    x = x.copy()
    state = (
        x,
        loss.copy(),
        grad.copy(),
        np.ones(n_rows, np.int64),  # evaluations
        np.zeros(n_rows, np.int64),  # iterations
        np.zeros((n_rows, max_iter, n_params), x.dtype),  # history: steps
        np.zeros((n_rows, max_iter, n_params), x.dtype),  # history: gradient changes
        np.zeros((n_rows, max_iter), x.dtype),  # history: 1 / curvature
        np.zeros(n_rows, np.int64),  # history: pairs kept
        np.empty_like(x),  # direction
        np.empty_like(loss),  # slope
        np.empty_like(loss),  # step
        np.zeros(n_rows, np.bool_),  # running
        np.zeros(n_rows, np.int64),  # trials of the current line search
        np.zeros(n_rows, np.bool_),  # search: found
        loss.copy(),  # search: best loss
        grad.copy(),  # search: best gradient
        np.zeros_like(loss),  # search: best step
    )
    _begin(*state, constants)
    while state[12].any():
        rows = np.flatnonzero(state[12])
        trial_loss, trial_grad = evaluate(rows, _trial_points(x, state[11], state[9], rows))
        _advance(*state, rows, trial_loss, trial_grad, constants, limits)
    return x


@njit(**_OPTIONS)
def _trial_points(x, step, direction, rows):
    points = np.empty((len(rows), x.shape[1]), x.dtype)
    for k in range(len(rows)):
        for p in range(x.shape[1]):
            points[k, p] = x[rows[k], p] + step[rows[k]] * direction[rows[k], p]
    return points


@njit(**_OPTIONS)
def _dot(a, b):
    """NumPy's ``(a * b).sum()`` of a few numbers: from zero, in order."""
    total = a.dtype.type(0.0)
    for p in range(len(a)):
        total += a[p] * b[p]
    return total


@njit(**_OPTIONS)
def _largest(a):
    """``np.abs(a).max()``: NaN if any element is NaN."""
    largest = abs(a[0])
    for p in range(1, len(a)):
        value = abs(a[p])
        if value > largest or value != value:
            largest = value
    return largest


@njit(**_OPTIONS)
def _minimum(a, b):
    return a if (a != a or a <= b) else b


@njit(**_OPTIONS)
def _begin(x, loss, grad, evals, iterations, steps, changes, inverse, pairs, direction, slope, step,
           running, trials, found, best_loss, best_grad, best_step, constants):  # fmt: skip
    lr, tol = constants[0], constants[1]
    one = x.dtype.type(1.0)
    for c in range(len(x)):
        total = x.dtype.type(0.0)
        for p in range(x.shape[1]):
            direction[c, p] = -grad[c, p]
            total += abs(grad[c, p])
        slope[c] = _dot(grad[c], direction[c])
        step[c] = lr * _minimum(one / total, one)
        running[c] = _largest(grad[c]) > tol and slope[c] <= -tol


@njit(**_OPTIONS)
def _advance(x, loss, grad, evals, iterations, steps, changes, inverse, pairs, direction, slope, step,
             running, trials, found, best_loss, best_grad, best_step, rows, trial_loss, trial_grad,
             constants, limits):  # fmt: skip
    lr, tol, armijo, wolfe, grow_min, grow_max, shrink_min, shrink_max, back_max, tiny_step, min_curvature = (
        constants[:11]
    )
    max_iter, max_eval, max_trials = limits[0], limits[1], limits[2]
    n_params = x.shape[1]
    zero, one, two = x.dtype.type(0.0), x.dtype.type(1.0), x.dtype.type(2.0)
    taken = np.empty(n_params, x.dtype)
    change = np.empty(n_params, x.dtype)
    going = np.zeros(len(x), np.bool_)
    for k in range(len(rows)):
        c = rows[k]
        evals[c] += 1
        trials[c] += 1
        # The line search (solver._Search.update).
        t_loss, t_grad = trial_loss[k], trial_grad[k]
        t_slope = _dot(t_grad, direction[c])
        sufficient = t_loss <= loss[c] + armijo * step[c] * slope[c]
        better = sufficient and not (found[c] and t_loss > best_loss[c])
        if better:
            best_loss[c] = t_loss
            best_grad[c] = t_grad
            best_step[c] = step[c]
            found[c] = True
        longer = better and t_slope < wolfe * slope[c]
        back = better and t_slope > -wolfe * slope[c]
        shorter = not better and not found[c]
        secant = step[c] * slope[c] / (slope[c] - t_slope)
        grown = secant if t_slope > slope[c] else grow_max * step[c]
        grown = _minimum(maximum(grown, grow_min * step[c]), grow_max * step[c])
        inside = _minimum(maximum(secant, shrink_min * step[c]), back_max * step[c])
        curve = t_loss - loss[c] - slope[c] * step[c]
        shrunk = -slope[c] * step[c] * step[c] / (two * curve)
        if not (np.isfinite(shrunk) and curve > 0):
            shrunk = shrink_max * step[c]
        shrunk = _minimum(maximum(shrunk, shrink_min * step[c]), shrink_max * step[c])
        next_step = grown if longer else (inside if back else shrunk)
        for p in range(n_params):
            taken[p] = next_step * direction[c, p]
        searching = (longer or ((back or shorter) and _largest(taken) > tiny_step)) and trials[c] < max_trials
        if searching:
            step[c] = next_step
        running[c] = searching
        if searching or not found[c]:
            continue
        # Accepted: the curvature pair, the move, the stopping tests (solver._lbfgs).
        for p in range(n_params):
            taken[p] = best_step[c] * direction[c, p]
            change[p] = best_grad[c, p] - grad[c, p]
        curvature = _dot(taken, change)
        if curvature > min_curvature:
            slot = pairs[c]
            steps[c, slot] = taken
            changes[c, slot] = change
            inverse[c, slot] = one / curvature
            pairs[c] = slot + 1
        previous = loss[c]
        for p in range(n_params):
            x[c, p] = x[c, p] + taken[p]
        loss[c] = best_loss[c]
        grad[c] = best_grad[c]
        iterations[c] += 1
        going[c] = (
            iterations[c] < max_iter
            and evals[c] < max_eval
            and _largest(grad[c]) > tol
            and _largest(taken) > tol
            and abs(loss[c] - previous) >= tol
        )
    if not going.any():
        return
    used = pairs.max()
    tiny = constants[11]
    alphas = np.empty(used, x.dtype)
    q = np.empty(n_params, x.dtype)
    for c in np.flatnonzero(going):
        # The two-loop recursion (solver._History.direction), over the slots any row uses.
        for p in range(n_params):
            q[p] = -grad[c, p]
        for slot in range(used - 1, -1, -1):
            alpha = inverse[c, slot] * _dot(steps[c, slot], q) if slot < pairs[c] else zero
            for p in range(n_params):
                q[p] = q[p] - alpha * changes[c, slot, p]
            alphas[slot] = alpha
        if used:
            newest = max(pairs[c] - 1, 0)
            s, y = steps[c, newest], changes[c, newest]
            gamma = _dot(s, y) / maximum(_dot(y, y), tiny) if pairs[c] > 0 else one
            for p in range(n_params):
                q[p] = q[p] * gamma
            for slot in range(used):
                beta = inverse[c, slot] * _dot(changes[c, slot], q)
                factor = alphas[slot] - beta if slot < pairs[c] else zero
                for p in range(n_params):
                    q[p] = q[p] + factor * steps[c, slot, p]
        new_slope = _dot(grad[c], q)
        if new_slope <= -tol:
            direction[c] = q
            slope[c] = new_slope
            step[c] = lr
            found[c] = False
            trials[c] = 0
            running[c] = True
