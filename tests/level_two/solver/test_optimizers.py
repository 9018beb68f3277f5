import pytest
import torch

from evseg_torch.backend import using_backend
from evseg_torch.level_two.solver.optimizers import adam, lbfgs

SOLVERS = {"lbfgs": lbfgs, "adam": adam}


def _problems(targets, scales, counts=None):
    """Scaled quadratics with a quartic term, one per row; ``counts`` records each row's evaluations."""

    def evaluate(rows, x):
        x = x.clone().requires_grad_()
        loss = scales[rows] * ((x - targets[rows]) ** 2).sum(dim=1) + (x**4).sum(dim=1) / 10
        loss.sum().backward()
        if counts is not None:
            counts.index_add_(0, rows, torch.ones_like(rows))
        return loss.detach(), x.grad

    return evaluate


def _rosenbrock(rows, x):
    x = x.clone().requires_grad_()
    loss = (1 - x[:, 0]) ** 2 + 100 * (x[:, 1] - x[:, 0] ** 2) ** 2
    loss.sum().backward()
    return loss.detach(), x.grad


TARGETS = torch.tensor([[3.0, -1.0], [0.5, 2.0], [-2.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
SCALES = torch.tensor([1.0, 40.0, 0.05, 3.0], dtype=torch.float64)


def test_lbfgs_minimises_each_problem():
    evaluate = _problems(TARGETS, SCALES)
    found = lbfgs(evaluate, torch.zeros(4, 2, dtype=torch.float64), max_iter=50, tol=1e-12)
    assert found.shape == (4, 2)
    _, grad = evaluate(torch.arange(4), found)
    assert grad.abs().max() < 1e-5


def test_lbfgs_rosenbrock():
    start = torch.tensor([[-1.2, 1.0], [0.0, 0.0]], dtype=torch.float64)
    found = lbfgs(_rosenbrock, start, max_iter=200, tol=1e-12)
    torch.testing.assert_close(found, torch.ones(2, 2, dtype=torch.float64), atol=1e-4, rtol=0)


def test_adam_approaches_each_minimum():
    evaluate = _problems(TARGETS[[0, 3]], torch.ones(2, dtype=torch.float64))
    found = adam(evaluate, torch.zeros(2, 2, dtype=torch.float64), max_iter=600, lr=0.05, tol=0)
    _, grad = evaluate(torch.arange(2), found)
    assert grad.abs().max() < 1e-2


@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_batched_equals_solo_bit_for_bit(name):
    # Each problem takes its own path: solved with the others it lands where it lands alone.
    evaluate = _problems(TARGETS, SCALES)
    start = torch.tensor([[0.0, 0.0], [1.0, 1.0], [5.0, -3.0], [1.0, 1.0]], dtype=torch.float64)
    together = SOLVERS[name](evaluate, start, max_iter=8)
    for row in range(4):
        alone = SOLVERS[name](_problems(TARGETS[[row]], SCALES[[row]]), start[[row]], max_iter=8)
        assert torch.equal(together[row], alone[0])


@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_loss_never_rises_and_start_is_kept(name):
    evaluate = _problems(TARGETS, SCALES)
    start = torch.tensor([[0.0, 0.0], [1.0, 1.0], [5.0, -3.0], [1.0, 1.0]], dtype=torch.float64)
    before = start.clone()
    found = SOLVERS[name](evaluate, start, max_iter=4)
    assert torch.equal(start, before)  # the caller's tensor is not modified
    every = torch.arange(4)
    if name == "lbfgs":  # accepted steps only decrease the loss (Adam's steps need not)
        assert torch.all(evaluate(every, found)[0] <= evaluate(every, start)[0])


def test_converged_rows_drop_out():
    # A problem that starts at its minimum is evaluated once; the others go on without it.
    counts = torch.zeros(2, dtype=torch.long)
    targets = torch.tensor([[0.0, 0.0], [3.0, -1.0]], dtype=torch.float64)
    evaluate = _problems(targets, torch.ones(2, dtype=torch.float64), counts)
    found = lbfgs(evaluate, torch.zeros(2, 2, dtype=torch.float64), max_iter=10)
    assert counts[0] == 1 and counts[1] > 1
    assert torch.equal(found[0], torch.zeros(2, dtype=torch.float64))


def test_evaluation_budget():
    counts = torch.zeros(1, dtype=torch.long)

    def evaluate(rows, x):
        counts.index_add_(0, rows, torch.ones_like(rows))
        return _rosenbrock(rows, x)

    lbfgs(evaluate, torch.tensor([[-1.2, 1.0]], dtype=torch.float64), max_iter=6, tol=0)
    assert 1 < counts[0] <= 6 * 5 // 4


def test_line_search_backs_off_from_non_finite_losses():
    # The loss is infinite beyond |x| = 2: the first trial lands there, and the search shortens it.
    def evaluate(rows, x):
        x = x.clone().requires_grad_()
        loss = ((x - 1.5) ** 2).sum(dim=1)
        loss.sum().backward()
        outside = x.detach().abs().amax(dim=1) > 2
        return torch.where(outside, torch.inf, loss.detach()), x.grad

    found = lbfgs(evaluate, torch.tensor([[-1.0, -1.0]], dtype=torch.float64), lr=10.0, max_iter=20)
    torch.testing.assert_close(found, torch.full((1, 2), 1.5, dtype=torch.float64), atol=1e-4, rtol=0)


@pytest.mark.parametrize("precision", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    ("max_iter", "lr", "tol"), [(6, 1.0, 0.0), (20, 1.0, 1e-6), (50, 10.0, 1e-12), (8, 0.3, 1e-6)]
)
def test_compiled_bookkeeping_follows_the_numpy_rounds(precision, max_iter, lr, tol):
    # The compiled rounds (kernels.solver) ask for the same evaluations and land where the NumPy rounds do.
    pytest.importorskip("numba")

    start = torch.tensor([[0.0, 0.0], [1.0, 1.0], [5.0, -3.0], [-1.2, 1.0]], dtype=precision)

    def run():
        asked = []

        problems = _problems(TARGETS.to(precision), SCALES.to(precision))

        def evaluate(rows, x):
            asked.append(rows.tolist())
            return problems(rows, x)

        found = lbfgs(evaluate, start, max_iter=max_iter, lr=lr, tol=tol)
        rosenbrock = lbfgs(_rosenbrock, start, max_iter=max_iter, lr=lr, tol=tol)
        return found, rosenbrock, asked

    compiled = run()
    with using_backend("torch"):
        numpy_rounds = run()
    assert compiled[2] == numpy_rounds[2]
    for found, expected in zip(compiled[:2], numpy_rounds[:2], strict=True):
        torch.testing.assert_close(found, expected, rtol=1e-5, atol=1e-6)
