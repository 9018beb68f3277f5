import numpy as np
import pytest
import torch

from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.events import EventBatch, batch_windows
from evseg_torch.level_two.image.splat import extent_mask, splat_events
from evseg_torch.level_two.image.warp import LinearWarp, sum_ignoring_padding
from evseg_torch.level_two.objectives.contrast import (
    CONTRAST_OBJECTIVES,
    ContrastLoss,
    contrast_loss,
    image_variance,
    normalized_variance,
    padded_contrast_loss,
    warp_area_element,
    warped_contrast_loss,
    warped_contrast_loss_and_grad,
)
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.level_two.solver.crops import fit_crops, gather_members
from evseg_torch.motion import Affine4, Rotation3D, Translation
from tests.helpers.level_two import (
    DURATION,
    SIZE,
    TRUTH,
    displacement_error,
    edge_points,
    edge_scene,
    moving_events,
)

SMALL = [Translation((8, 8)), Affine4((8, 8)), Rotation3D((8, 8))]


def _small_events(n=20, seed=0):
    generator = torch.Generator().manual_seed(seed)
    xy = 2.0 + torch.rand(n, 2, generator=generator, dtype=torch.float64) * 3.0
    t = torch.rand(n, generator=generator, dtype=torch.float64) * 0.05
    return EventBatch(xy, t, torch.ones(n, dtype=torch.float64))


def _concatenated(windows):
    """The events of several single windows as one window (a batch's ``lengths`` is no event field)."""
    return EventBatch(*(torch.cat([getattr(w, name) for w in windows]) for name in ("xy", "t", "p")))


class TestObjectives:
    def test_smoke(self, device, dtype):
        image = torch.rand(3, 8, 8, device=device, dtype=dtype)
        torch.testing.assert_close(image_variance(image), image.flatten(1).var(dim=1, unbiased=False))
        torch.testing.assert_close(
            normalized_variance(image, image), torch.ones(3, device=device, dtype=dtype)
        )

    def test_cardinality(self):
        assert image_variance(torch.rand(2, 3, 8, 8)).shape == (2, 3)
        assert normalized_variance(torch.rand(2, 3, 8, 8), torch.rand(3, 8, 8)).shape == (2, 3)
        assert set(CONTRAST_OBJECTIVES) == {"variance", "normalized_variance"}

    def test_exception(self):
        with pytest.raises(ShapeError, match=r"iwe must have shape \(\.\.\., H, W\)"):
            image_variance(torch.rand(5))
        with pytest.raises(ShapeError, match=r"reference must be a torch\.Tensor"):
            normalized_variance(torch.rand(8, 8), None)

    def test_sharper_image_has_higher_variance(self):
        stacked = splat_events(torch.full((50, 2), 4.0), (9, 9))
        spread = splat_events(torch.rand(50, 2) * 8, (9, 9))
        assert image_variance(stacked) > image_variance(spread)
        assert normalized_variance(stacked, spread) > 1


class TestMaskedVariance:
    def test_equals_the_variance_of_each_image_alone(self, device, dtype):
        images = torch.rand(2, 7, 9, device=device, dtype=dtype)
        extent = torch.tensor([[5, 6], [7, 9]], device=device)
        mask = extent_mask(extent, (7, 9))
        masked = image_variance(images, mask=mask)
        torch.testing.assert_close(masked[0], image_variance(images[0, :5, :6]))
        torch.testing.assert_close(masked[1], image_variance(images[1]))
        torch.testing.assert_close(
            normalized_variance(images, images.flip(0), mask=mask)[1],
            normalized_variance(images[1], images[0]),
        )

    def test_bit_for_bit_in_any_canvas(self):
        # The same image with its gradient, alone and in a larger canvas whatever lies beyond it.
        image = torch.rand(5, 6, dtype=torch.float64, requires_grad=True)
        canvas = torch.rand(9, 11, dtype=torch.float64)
        embedded = canvas.index_put((torch.arange(5)[:, None], torch.arange(6)), image)
        alone = image_variance(image, mask=torch.ones(5, 6, dtype=torch.bool))
        within = image_variance(embedded, mask=extent_mask(torch.tensor([5, 6]), (9, 11)))
        assert torch.equal(alone, within)
        assert torch.equal(*(torch.autograd.grad(value, image)[0] for value in (alone, within)))

    def test_gradcheck(self):
        images = torch.rand(2, 5, 6, dtype=torch.float64, requires_grad=True)
        mask = extent_mask(torch.tensor([[3, 4], [5, 6]]), (5, 6))
        assert torch.autograd.gradcheck(lambda x: image_variance(x, mask=mask), (images,), fast_mode=True)


class TestSumIgnoringPadding:
    @pytest.mark.parametrize("length", [1, 255, 256, 257, 1000])
    def test_zeros_appended_change_nothing(self, length, dtype):
        values = torch.randn(3, length, dtype=dtype, generator=torch.Generator().manual_seed(length)) * 100
        padded = torch.cat([values, torch.zeros(3, 300, dtype=dtype)], dim=1)
        assert torch.equal(sum_ignoring_padding(values), sum_ignoring_padding(padded))
        # Another summation order: the two sums may differ by rounding in every one of up to 1000 terms.
        scale = values.abs().sum(dim=1) * length * torch.finfo(dtype).eps
        assert torch.all((sum_ignoring_padding(values) - values.sum(dim=1)).abs() <= scale)


class TestContrastLoss:
    def test_smoke(self, device, dtype):
        events = _small_events().to(device=device, dtype=dtype)
        loss = contrast_loss(Affine4((8, 8)), events, torch.zeros(2, 4, device=device, dtype=dtype))
        assert loss.dtype == dtype and torch.all(loss < 0)

    @pytest.mark.parametrize("objective", sorted(CONTRAST_OBJECTIVES))
    def test_cardinality(self, objective):
        events, model = _small_events(), Affine4((8, 8))
        params = torch.zeros(3, 4, dtype=torch.float64)
        assert contrast_loss(model, events, params, objective=objective).shape == (3,)
        weights = torch.rand(3, 20, dtype=torch.float64)
        assert contrast_loss(model, events, params, weights, objective=objective).shape == (3,)

    def test_exception(self):
        events, model = _small_events(), Affine4((8, 8))
        with pytest.raises(ConfigError, match="unknown contrast objective 'sharpness'"):
            contrast_loss(model, events, torch.zeros(1, 4), objective="sharpness")
        with pytest.raises(ShapeError, match=r"params must be \(K, P\)"):
            contrast_loss(model, events, torch.zeros(4))
        with pytest.raises(ShapeError, match=r"params must be \(\.\.\., 4\)"):
            contrast_loss(model, events, torch.zeros(1, 3, dtype=torch.float64))
        with pytest.raises(ShapeError, match="weights must be"):
            contrast_loss(model, events, torch.zeros(1, 4), torch.ones(1, 7))
        with pytest.raises(ConfigError, match="collapse_weight"):
            contrast_loss(model, events, torch.zeros(1, 4), collapse_weight=-1.0)

    def test_weights_select_cluster_events(self):
        events, model = _small_events(40), Affine4((8, 8))
        params = torch.rand(2, 4, dtype=torch.float64)
        member = torch.rand(40) < 0.5
        weights = torch.stack([member, ~member]).double()
        loss = contrast_loss(model, events, params, weights)
        for k, mask in enumerate((member, ~member)):
            own = EventBatch(events.xy[mask], events.t[mask], events.p[mask])
            torch.testing.assert_close(loss[k], contrast_loss(model, own, params[k : k + 1])[0])

    def test_true_motion_is_sharpest(self):
        model, truth, events, start = edge_scene("affine4")
        loss = contrast_loss(model, events, torch.tensor(np.stack([truth, start, np.zeros(4)])))
        assert loss[0] < loss[1] and loss[0] < loss[2]

    @pytest.mark.parametrize("model", SMALL, ids=lambda m: m.name)
    def test_gradcheck(self, model):
        events = _small_events()
        params = torch.tensor(np.linspace(0.5, 2.0, model.n_params))[None].repeat(2, 1).requires_grad_()
        weights = torch.rand(2, 20, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda p, w: contrast_loss(model, events, p, w, objective="normalized_variance"),
            (params, weights),
            fast_mode=True,
        )

    def test_module(self):
        events, model = _small_events(), Affine4((8, 8))
        params = torch.rand(2, 3, 4, dtype=torch.float64)
        loss = ContrastLoss(model, objective="normalized_variance", reduction="none")
        batched = loss([events, events], params)
        assert batched.shape == (2, 3)
        for b in range(2):
            torch.testing.assert_close(
                batched[b], contrast_loss(model, events, params[b], objective="normalized_variance")
            )
        mean = ContrastLoss(model)(events, params[0])
        torch.testing.assert_close(mean, contrast_loss(model, events, params[0]).mean())
        assert "objective='normalized_variance'" in repr(loss)
        with pytest.raises(ShapeError, match=r"params must be \(B, K, P\)"):
            loss([events, events], params[0])
        with pytest.raises(ConfigError, match="reduction"):
            ContrastLoss(model, reduction="max")

    @pytest.mark.parametrize("objective", sorted(CONTRAST_OBJECTIVES))
    def test_padded_batch_equals_list(self, objective):
        model = Affine4((8, 8))
        windows = [_small_events(20, seed=0), _small_events(9, seed=1), _small_events(14, seed=2)]
        params = torch.rand(3, 2, 4, dtype=torch.float64)
        loss = ContrastLoss(model, objective=objective, reduction="none")
        batch = batch_windows(windows)
        torch.testing.assert_close(loss(batch, params), loss(windows, params))
        weights = [torch.rand(2, len(w), dtype=torch.float64) for w in windows]
        # Padding counts 0 whatever its weights hold, NaN included.
        padded = torch.full((3, 2, 20), float("nan"), dtype=torch.float64)
        for row, own in enumerate(weights):
            padded[row, :, : own.shape[1]] = own
        torch.testing.assert_close(loss(batch, params, padded), loss(windows, params, weights))
        torch.testing.assert_close(
            padded_contrast_loss(model, batch, params, padded, objective=objective),
            loss(batch, params, padded),
        )

    def test_padded_batch_gradcheck(self):
        model = Affine4((8, 8))
        batch = batch_windows([_small_events(12, seed=0), _small_events(7, seed=1)])
        params = torch.rand(2, 2, 4, dtype=torch.float64, requires_grad=True)
        weights = torch.rand(2, 2, 12, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda p, w: padded_contrast_loss(model, batch, p, w, objective="normalized_variance"),
            (params, weights),
            fast_mode=True,
        )

    def test_padded_batch_exception(self):
        model = Affine4((8, 8))
        batch = batch_windows([_small_events(12, seed=0), _small_events(7, seed=1)])
        loss = ContrastLoss(model, reduction="none")
        with pytest.raises(ShapeError, match=r"params must be \(B, K, 4\) with B = 2"):
            loss(batch, torch.zeros(3, 2, 4, dtype=torch.float64))
        with pytest.raises(ShapeError, match=r"params must be \(B, K, 4\)"):
            loss(batch, torch.zeros(2, 2, 3, dtype=torch.float64))
        with pytest.raises(ShapeError, match=r"weights must be \(B, K, N_max\) = \(2, 2, 12\)"):
            loss(batch, torch.zeros(2, 2, 4, dtype=torch.float64), torch.ones(2, 2, 7, dtype=torch.float64))
        with pytest.raises(ShapeError, match="weights must be a tensor"):
            loss(batch, torch.zeros(2, 2, 4, dtype=torch.float64), [None, None])
        with pytest.raises(ShapeError, match="padded batch"):
            padded_contrast_loss(model, _small_events(), torch.zeros(1, 2, 4, dtype=torch.float64))


class TestCollapseGuard:
    def test_area_element(self):
        events = _small_events()
        d, r = 4.0, 3.0
        area = warp_area_element(
            Affine4((8, 8)), events, torch.tensor([[1.0, 2.0, d, r]], dtype=torch.float64)
        )
        torch.testing.assert_close(area[0], (1 - events.t * d) ** 2 + (events.t * r) ** 2)
        area = warp_area_element(
            Translation((8, 8)), events, torch.tensor([[50.0, -20.0]], dtype=torch.float64)
        )
        torch.testing.assert_close(area, torch.ones_like(area))

    def test_guard_prevents_collapse(self):
        # Dense texture: plain variance prefers packing events into less area.
        model, truth, events, _ = edge_scene("affine4", n_points=8000, n_segments=40, integer=False)
        start = torch.tensor(truth)[None]
        true_area = warp_area_element(model, events, start).mean()
        plain = ContrastMaximization(model, collapse_weight=0.0, max_iter=30)(events, start)
        guarded = ContrastMaximization(model, max_iter=30)(events, start)
        assert warp_area_element(model, events, plain).mean() / true_area < 0.95
        assert displacement_error(model, plain[0], truth, events, DURATION) > 0.1
        assert abs(warp_area_element(model, events, guarded).mean() / true_area - 1) < 0.01
        assert displacement_error(model, guarded[0], truth, events, DURATION) < 0.05


class TestContrastMaximization:
    @pytest.mark.parametrize("name", sorted(TRUTH))
    def test_recovers_motion(self, name, device, dtype):
        model, truth, events, start = edge_scene(name, dtype=dtype, device=device)
        cmax = ContrastMaximization(model, max_iter=30)
        fitted = cmax(events, torch.tensor(start, dtype=dtype, device=device)[None])
        assert fitted.shape == (1, model.n_params) and fitted.dtype == dtype
        assert displacement_error(model, start, truth, events, DURATION) > 0.25
        assert displacement_error(model, fitted[0], truth, events, DURATION) < 0.02

    @pytest.mark.parametrize(
        ("name", "bound"), [("translation", 0.02), ("rotation3d", 0.02), ("affine4", 0.04)]
    )
    def test_recovers_motion_subpixel_events(self, name, bound):
        # Off-pixel events expose the pixel grid's pull on bilinear voting, hence affine4's wider bound.
        model, truth, events, start = edge_scene(name, integer=False)
        fitted = ContrastMaximization(model, max_iter=30)(events, torch.tensor(start)[None])
        assert displacement_error(model, fitted[0], truth, events, DURATION) < bound

    def test_adam(self):
        model, truth, events, start = edge_scene("translation")
        cmax = ContrastMaximization(model, optimizer="adam", max_iter=150, lr=0.2)
        fitted = cmax(events, torch.tensor(start)[None])
        assert displacement_error(model, fitted[0], truth, events, DURATION) < 0.02

    def test_clusters_fitted_together(self):
        # Two objects moving differently: the joint fit of both equals fitting each on its own events.
        model = Affine4(SIZE)
        rng = np.random.default_rng(3)
        truths = np.array([[600.0, -400.0, 2.0, 3.0], [-300.0, 500.0, -2.0, 1.0]])
        batches = [
            moving_events(
                model, truth, edge_points(SIZE, 4000, rng, box=box), DURATION, rng, noise=0.2, integer=True
            )
            for truth, box in zip(truths, [(0.05, 0.2, 0.5, 0.8), (0.5, 0.2, 0.95, 0.8)], strict=True)
        ]
        events = _concatenated(batches)
        labels = torch.cat([torch.full((len(b),), k) for k, b in enumerate(batches)])
        weights = torch.nn.functional.one_hot(labels, 2).T.double()
        cmax = ContrastMaximization(model, max_iter=50)
        with torch.no_grad():  # a segmenter may call the refit under no_grad
            fitted = cmax(events, torch.tensor(truths * 1.3), weights)
        for k, own in enumerate(batches):
            alone = cmax(own, torch.tensor(truths[k : k + 1] * 1.3))[0]
            assert displacement_error(model, fitted[k], alone.numpy(), own, DURATION) < 0.005
            assert displacement_error(model, fitted[k], truths[k], own, DURATION) < 0.04

    def test_loss_decreases(self):
        model, _, events, start = edge_scene("rotation3d")
        start = torch.tensor(start)[None]
        fitted = ContrastMaximization(model, max_iter=5)(events, start)
        assert contrast_loss(model, events, fitted) < contrast_loss(model, events, start)

    def test_no_time_span_returns_start(self):
        events = EventBatch(torch.rand(10, 2) * 7, torch.zeros(10), torch.ones(10))
        start = torch.rand(2, 2)
        torch.testing.assert_close(ContrastMaximization(Translation((8, 8)))(events, start), start)

    def test_exception(self):
        model, events = Affine4((8, 8)), _small_events()
        cmax = ContrastMaximization(model)
        with pytest.raises(ShapeError, match=r"init_params must be \(K, 4\)"):
            cmax(events, torch.zeros(4, dtype=torch.float64))
        with pytest.raises(ShapeError, match=r"weights must be \(K, N\)"):
            cmax(events, torch.zeros(2, 4, dtype=torch.float64), torch.ones(20, dtype=torch.float64))
        with pytest.raises(ConfigError, match="optimizer must be 'lbfgs' or 'adam'"):
            ContrastMaximization(model, optimizer="sgd")
        with pytest.raises(ModelError, match="init_params hold NaN or inf"):
            cmax(events, torch.full((2, 4), float("inf"), dtype=torch.float64))
        with pytest.raises(ConfigError, match="max_iter must be an integer of at least 1, got True"):
            ContrastMaximization(model, max_iter=True)
        with pytest.raises(ConfigError, match="unknown contrast objective"):
            ContrastMaximization(model, objective="entropy")

    def test_module_repr(self):
        assert "optimizer='lbfgs'" in repr(ContrastMaximization(Affine4((8, 8))))


def _fit_windows(device="cpu"):
    """Three windows of translating blobs (clusters in crops and on the whole sensor, from 30% off), of
    different sizes, with their pools padded to three clusters (the third window's third cluster has no
    events); as a padded batch."""
    windows = [
        _corner_and_sensor(seed=0),
        _corner_and_sensor(seed=1, corner=False),
        _corner_and_sensor(seed=2),
    ]
    model = windows[0][0]
    events = [window[3].to(device=device, dtype=torch.float32) for window in windows]
    longest = max(len(window) for window in events)
    weights = torch.zeros(3, 3, longest, device=device)
    start = torch.zeros(3, 3, 2, device=device)
    for row, (*_, own, start_own) in enumerate(windows):
        weights[row, : own.shape[0], : own.shape[1]] = own
        start[row, : len(start_own)] = start_own
    start[1, 2] = torch.tensor([5.0, 7.0])  # no events: kept
    return model, events, batch_windows(events), start, weights


class TestBatchedFits:
    @pytest.mark.parametrize("optimizer", ["lbfgs", "adam"])
    def test_batch_equals_windows_alone(self, device, optimizer):
        # Every window's fits run in lockstep with their own optimiser state: each lands where it lands
        # alone (bit for bit on the CPU), whatever the other windows and the padding.
        model, events, batch, start, weights = _fit_windows(device)
        cmax = ContrastMaximization(model, max_iter=8, optimizer=optimizer)
        fitted = cmax(batch, start, weights)
        assert fitted.shape == (3, 3, 2) and fitted.device.type == device.type
        for row, own in enumerate(events):
            count = 2 if row == 1 else 3
            alone = cmax(own, start[row, :count], weights[row, :count, : len(own)])
            # On CUDA, scatter-adds sum in no fixed order, so batched and solo paths part a little (0.22 of
            # ~200 px/s on an H200): equal to a hundredth of a pixel over the window; on the CPU bit for bit.
            torch.testing.assert_close(fitted[row, :count], alone, atol=0.01 / DURATION, rtol=0)
            if device.type == "cpu":
                assert torch.equal(fitted[row, :count], alone)
        assert torch.equal(fitted[1, 2], start[1, 2])
        # Every cluster moved from its start towards its blob's motion.
        assert (fitted[0] - start[0]).abs().amax() > 10

    def test_batch_without_weights(self, device):
        model, events, batch, start, _ = _fit_windows(device)
        cmax = ContrastMaximization(model, max_iter=4)
        fitted = cmax(batch, start[:, :2])
        assert torch.all((fitted - start[:, :2]).abs().amax(dim=2) > 1)  # every cluster is fitted
        for row, own in enumerate(events):
            alone = cmax(own, start[row, :2])
            torch.testing.assert_close(fitted[row], alone, atol=0.01 / DURATION, rtol=0)
            if device.type == "cpu":
                assert torch.equal(fitted[row], alone)

    def test_window_without_time_span_keeps_its_start(self):
        model, events, _, start, weights = _fit_windows()
        still = EventBatch(events[2].xy, torch.zeros_like(events[2].t), events[2].p)
        batch = batch_windows([events[0], still])
        fitted = ContrastMaximization(model, max_iter=3)(batch, start[[0, 2]], weights[[0, 2]])
        assert torch.equal(fitted[1], start[2]) and not torch.equal(fitted[0], start[0])

    def test_exception(self):
        model, _, batch, start, weights = _fit_windows()
        cmax = ContrastMaximization(model)
        with pytest.raises(ShapeError, match=r"init_params must be \(B, K, 2\) with B = 3 windows"):
            cmax(batch, start[0])
        with pytest.raises(ShapeError, match=r"weights must be \(B, K, N_max\)"):
            cmax(batch, start, weights[..., :10])


def _corner_and_sensor(seed=0, corner=True):
    """Translating edges: a blob in the top-left corner, one spanning the sensor and (``corner``) a
    smaller blob in the bottom-right corner, shuffled together; with one-hot weights and 30% off starts."""
    model = Translation(SIZE)
    truths = np.array([[400.0, 300.0], [-300.0, 200.0], [-350.0, -250.0]])
    boxes = [(0.03, 0.05, 0.2, 0.25), (0.02, 0.02, 0.98, 0.98), (0.85, 0.8, 0.97, 0.97)]
    shapes = [(1500, 6), (5000, 30), (800, 4)]
    count = 3 if corner else 2
    rng = np.random.default_rng(seed)
    batches = [
        moving_events(
            model,
            truth,
            edge_points(SIZE, n, rng, n_segments=s, box=box),
            DURATION,
            rng,
            noise=0.2,
            integer=True,
        )
        for truth, box, (n, s) in list(zip(truths, boxes, shapes, strict=True))[:count]
    ]
    events = _concatenated(batches)
    labels = torch.cat([torch.full((len(b),), k) for k, b in enumerate(batches)])
    order = torch.as_tensor(rng.permutation(len(labels)))
    events = EventBatch(events.xy[order], events.t[order], events.p[order])
    weights = torch.nn.functional.one_hot(labels[order], count).T.double()
    start = torch.tensor(truths[:count] * np.array([[1.3, 0.7], [0.7, 1.3], [0.7, 0.7]])[:count])
    return model, truths[:count], batches, events, weights, start


class TestCrops:
    def test_gather_members(self):
        events = EventBatch(
            torch.arange(14.0).view(7, 2), torch.linspace(0, 0.01, 7), torch.tensor([1.0, -1] * 3 + [1.0])
        )
        weights = torch.tensor([[1.0, 0, 0.5, 0, 0, 2.0, 0], [0, 0, 0, 0.3, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0]])
        own, padded = gather_members(events, weights)
        assert own.xy.shape == (3, 3, 2) and own.t.shape == own.p.shape == padded.shape == (3, 3)
        for k, members in enumerate(([0, 2, 5], [3], [])):
            n = len(members)
            torch.testing.assert_close(own.xy[k, :n], events.xy[members])
            torch.testing.assert_close(own.t[k, :n], events.t[members])
            torch.testing.assert_close(own.p[k, :n], events.p[members])
            torch.testing.assert_close(padded[k, :n], weights[k, members])
            assert torch.all(padded[k, n:] == 0)
        # The gathered, padded events give every cluster the loss of its weighted events.
        model, params = Affine4((8, 8)), torch.rand(3, 4) * torch.tensor([50.0, 50.0, 2.0, 2.0])
        torch.testing.assert_close(
            contrast_loss(model, own, params, padded), contrast_loss(model, events, params, weights)
        )

    def test_small_clusters_share_a_crop(self):
        model, *_, events, weights, start = _corner_and_sensor()
        own, padded = gather_members(events, weights)
        warp = LinearWarp.build(model, own, with_area=False)
        fits, origin = fit_crops(warp, padded, start, SIZE, torch.zeros(3, dtype=torch.long))
        height, width = SIZE
        assert [rows.tolist() for rows, _ in fits] == [[0, 2], [1]]
        (_, small_size), (_, whole_size) = fits
        assert whole_size == SIZE and small_size[0] * small_size[1] <= 0.25 * height * width
        assert torch.all(origin[1] == 0)
        shifted = warp._replace(xy=warp.xy - origin[:, None])
        for k in (0, 2):
            member = padded[k] != 0
            # Each cluster is moved by a whole number of pixels, into the crop, at the start and warped.
            assert torch.all(origin[k] == origin[k].round()) and torch.all(origin[k] >= 0)
            for xy in (shifted.xy[k, member], shifted.warped(start)[k, member]):
                assert xy.min() >= 0
                assert xy[:, 0].max() <= small_size[1] - 1 and xy[:, 1].max() <= small_size[0] - 1
        # The bottom-right blob's crop is moved back inside the sensor: it ends at the sensor's edge.
        assert (
            origin[2, 0] + small_size[1] - 1 == width - 1 and origin[2, 1] + small_size[0] - 1 == height - 1
        )

    def test_crops_per_window(self):
        # The same clusters in two windows of a batch: each window gets its own fits, crops first.
        model, *_, events, weights, start = _corner_and_sensor()
        own, padded = gather_members(events, weights)
        warp = LinearWarp.build(model, own, with_area=False)
        twice = warp.rows(torch.tensor([0, 1, 2, 0, 1, 2]))
        window = torch.tensor([0, 0, 0, 1, 1, 1])
        fits, origin = fit_crops(twice, padded.repeat(2, 1), start.repeat(2, 1), SIZE, window)
        assert [rows.tolist() for rows, _ in fits] == [[0, 2], [1], [3, 5], [4]]
        assert fits[0][1] == fits[2][1] and fits[1][1] == fits[3][1] == SIZE
        torch.testing.assert_close(origin[:3], origin[3:])
        # Not cropped: one fit per window, on the whole sensor.
        fits, origin = fit_crops(twice, padded.repeat(2, 1), start.repeat(2, 1), SIZE, window, cropped=False)
        assert [(rows.tolist(), size) for rows, size in fits] == [([0, 1, 2], SIZE), ([3, 4, 5], SIZE)]
        assert torch.all(origin == 0)

    def test_small_cluster_fitted_in_a_crop(self):
        # A blob in one corner is fitted in a crop, the cluster spanning the sensor on the whole sensor:
        # both land where fitting each alone on the whole sensor does (measured: 0.06% and 0.05% of the
        # displacement apart; up to 0.8% on other seeds, neighbouring optima of the pixel grid), and the
        # blob's translation is recovered from 30% off (measured: 1.0% of the displacement).
        model, truths, batches, events, weights, start = _corner_and_sensor(corner=False)
        cmax = ContrastMaximization(model, max_iter=30)
        fitted = cmax(events, start, weights)
        for k, own in enumerate(batches):
            alone = cmax(own, start[k : k + 1])[0]
            assert displacement_error(model, fitted[k], alone.numpy(), own, DURATION) < 0.01
        assert displacement_error(model, start[0], truths[0], batches[0], DURATION) > 0.25
        assert displacement_error(model, fitted[0], truths[0], batches[0], DURATION) < 0.02


def test_max_iter_of_one_call():
    # One module serves fits of several lengths: a call's max_iter equals a module built with it.
    model, _, batch, start, weights = _fit_windows()
    fitted = ContrastMaximization(model, max_iter=20)(batch, start, weights, max_iter=3)
    assert torch.equal(fitted, ContrastMaximization(model, max_iter=3)(batch, start, weights))
    with pytest.raises(ConfigError, match="max_iter must be an integer of at least 1"):
        ContrastMaximization(model)(batch, start, weights, max_iter=0)


def _gathered_clusters(model, seed=0, n=60):
    """Three clusters' gathered events (the third padded with zero-weight events) and their warp."""
    generator = torch.Generator().manual_seed(seed)
    xy = torch.rand(3, n, 2, generator=generator, dtype=torch.float64) * torch.tensor([30.0, 20.0]) + 1.0
    t = torch.rand(3, n, generator=generator, dtype=torch.float64) * DURATION
    weights = torch.rand(3, n, generator=generator, dtype=torch.float64)
    weights[2, n // 2 :] = 0
    params = torch.randn(3, model.n_params, generator=generator, dtype=torch.float64)
    params = params * torch.as_tensor(model.displacement_scale(DURATION)).reciprocal() * 3.0
    return LinearWarp.build(model, EventBatch(xy, t, torch.ones_like(t))), weights, params


@pytest.mark.parametrize("model", [Translation((24, 34)), Affine4((24, 34)), Rotation3D((24, 34))])
@pytest.mark.parametrize("objective", ["variance", "normalized_variance"])
@pytest.mark.parametrize("collapse_weight", [0.0, 0.375])
def test_loss_and_grad_by_hand_equal_autograd(model, objective, collapse_weight):
    # The fits' evaluations chain the gradient by hand; autograd of the same loss agrees.
    warp, weights, params = _gathered_clusters(model)
    extent = torch.tensor([[24, 34], [18, 30], [24, 34]])
    reference = torch.tensor([0.7, 1.1, 0.9], dtype=torch.float64)
    divisor = torch.tensor([2.0, 0.5, 1.5], dtype=torch.float64)
    args = ((24, 34), objective, 1.0, collapse_weight, reference)
    mask = extent_mask(extent, (24, 34))
    loss, grad = warped_contrast_loss_and_grad(warp, params, weights, *args, mask, divisor)
    leaf = params.clone().requires_grad_()
    expected = warped_contrast_loss(warp, leaf, weights, *args, extent) / divisor
    expected.sum().backward()
    torch.testing.assert_close(loss, expected.detach())
    torch.testing.assert_close(grad, leaf.grad)


def test_loss_and_grad_by_hand_ignore_padding_bit_for_bit():
    # A cluster padded with zero-weight events (to the longest cluster of a batch) keeps its loss and
    # gradient exactly: the fits in a batch take the steps they take alone.
    model = Affine4((24, 34))
    warp, weights, params = _gathered_clusters(model, n=300)
    args = ((24, 34), "variance", 1.0, 0.375, None, None)
    loss, grad = warped_contrast_loss_and_grad(warp, params, weights, *args)
    own = LinearWarp(warp.xy[2:, :150], warp.maps[:, 2:, :150])
    alone_loss, alone_grad = warped_contrast_loss_and_grad(own, params[2:], weights[2:, :150], *args)
    assert torch.equal(loss[2:], alone_loss) and torch.equal(grad[2:], alone_grad)
