import functools

import pytest
import torch

from evseg_torch.backend import using_backend
from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.events import EventBatch, batch_windows, to_torch
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.energy.data_term import (
    NORMALIZATIONS,
    DataCost,
    _margins,
    _overshoots,
    _select_by_kthvalue,
    _select_by_partition,
    data_cost,
    sample_bilinear,
)
from evseg_torch.level_two.image.splat import splat_events
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import Affine4, Translation

# EMSGC's data term (images at sigma 1, the global maximum, no polarity, no margin), which these tests
# check; level two's (the config's, the functions' defaults) where a test gives its settings.
EMSGC = {"sigma": 1.0, "normalization": "global", "polarity": False, "margin": 0}
emsgc_cost = functools.partial(data_cost, **EMSGC)
EmsgcCost = functools.partial(DataCost, **EMSGC)


def _edge_events(count=400, flow=(300.0, -100.0), size=(32, 40), seed=0, dtype=torch.float32):
    """A vertical line moving with constant flow, sampled on the pixel grid over 20 ms."""
    generator = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.rand(count, generator=generator, dtype=torch.float64) * 0.02).values
    y0 = torch.rand(count, generator=generator, dtype=torch.float64) * (size[0] - 12) + 6
    x = (12.0 + flow[0] * t).round()
    y = (y0 + flow[1] * t).round()
    return EventBatch(torch.stack([x, y], 1).to(dtype), t.to(dtype), torch.ones(count, dtype=dtype))


def _reference(model, events, params, size, sigma):
    """Independent implementation: grid_sample (align_corners=True: pixel centres at integers)."""
    warped = warp_events(model, events.xy, events.t, params)
    iwes = splat_events(warped, size, sigma=sigma)
    negative = 255.0 * (1 - iwes / iwes.max())
    height, width = size
    grid = torch.stack([2 * warped[..., 0] / (width - 1) - 1, 2 * warped[..., 1] / (height - 1) - 1], -1)
    values = torch.nn.functional.grid_sample(negative[:, None], grid[:, None], align_corners=True)[:, 0, 0]
    x, y = warped[..., 0], warped[..., 1]
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    return torch.where(inside, values, torch.full_like(values, 255.0)).T


class TestSampleBilinear:
    def test_exact_at_pixel_centres(self):
        image = torch.rand(2, 5, 6)
        rows, cols = torch.meshgrid(torch.arange(5.0), torch.arange(6.0), indexing="ij")
        xy = torch.stack([cols.flatten(), rows.flatten()], -1).expand(2, -1, -1)
        values, inside = sample_bilinear(image, xy)
        torch.testing.assert_close(values, image.flatten(1))
        assert inside.all()

    def test_outside(self):
        values, inside = sample_bilinear(torch.ones(1, 4, 4), torch.tensor([[[-0.1, 1], [1, 3.01], [3, 3]]]))
        assert inside.tolist() == [[False, False, True]]
        assert values.tolist() == [[0.0, 0.0, 1.0]]


def _windows(dtype=torch.float32):
    """Three windows of different sizes, and pools of different sizes whose models carry events 5, 0 and 4
    pixels beyond the sensor."""
    windows = [
        _edge_events(count=400, seed=0, dtype=dtype),
        _edge_events(count=250, flow=(-200.0, 50.0), seed=1, dtype=dtype),
        _edge_events(count=320, flow=(100.0, 150.0), seed=2, dtype=dtype),
    ]
    pools = [
        torch.tensor([[300.0, -100.0], [0.0, 0.0], [900.0, 900.0]], dtype=dtype),
        torch.tensor([[-200.0, 50.0], [100.0, 0.0]], dtype=dtype),
        torch.tensor([[100.0, 150.0], [900.0, 0.0], [0.0, 0.0]], dtype=dtype),
    ]
    return windows, pools


class TestSampleBilinearExtent:
    def test_reads_as_the_smaller_image(self):
        # An image in the top-left corner of a larger canvas reads as the image alone: the same values,
        # the same outside positions (the last row and column included).
        image = torch.rand(1, 4, 5)
        canvas = torch.rand(1, 7, 9)
        canvas[0, :4, :5] = image[0]
        xy = torch.tensor([[[0.0, 0.0], [4.0, 3.0], [3.5, 2.25], [4.01, 1.0], [1.0, 3.5], [6.0, 6.0]]])
        alone = sample_bilinear(image, xy)
        within = sample_bilinear(canvas, xy, extent=torch.tensor([[[4, 5]]]))
        assert torch.equal(within[1], alone[1]) and torch.equal(within[0], alone[0])
        assert alone[1].tolist() == [[True, True, True, False, False, False]]


class TestDataCostBatch:
    @pytest.mark.parametrize("normalization", NORMALIZATIONS)
    @pytest.mark.parametrize(("polarity", "margin"), [(False, 0), (True, None), (False, 3)])
    def test_batch_equals_windows_alone(self, device, normalization, polarity, margin):
        # The padded batch's costs of each window equal its costs alone (bit for bit on the CPU), also
        # where the windows' own margins differ (margin=None: 5, 0 and 4 pixels, see the next test);
        # padding events and models cost 255.
        windows, pools = _windows()
        model = Translation((32, 40))
        kwargs = {"normalization": normalization, "polarity": polarity, "margin": margin}
        params = torch.nn.utils.rnn.pad_sequence(pools, batch_first=True)
        valid = torch.tensor([[True, True, True], [True, True, False], [True, True, True]])
        batch = batch_windows(windows).to(device)
        cost = emsgc_cost(model, batch, params.to(device), valid=valid.to(device), **kwargs)
        assert cost.shape == (3, 400, 3) and cost.device.type == device.type
        for row, (window, pool) in enumerate(zip(windows, pools, strict=True)):
            alone = emsgc_cost(model, window.to(device), pool.to(device), **kwargs)
            own = cost[row, : len(window), : len(pool)]
            torch.testing.assert_close(own, alone, atol=1e-3, rtol=0)
            if device.type == "cpu":
                assert torch.equal(own, alone)
            assert torch.all(cost[row, len(window) :] == 255) and torch.all(cost[row, :, len(pool) :] == 255)

    @pytest.mark.parametrize(
        ("margin", "floors"),
        [
            (None, (0.9, 0.75)),
            (0, (0.9, 0.75)),
            (3, (0.9, 0.75)),
            (None, (None, 0.5)),
            (None, (0.6, None)),
            (None, (None, None)),
        ],
    )
    def test_compiled_images_equal_the_tensor_code(self, margin, floors):
        # Where Numba is installed, per-polarity images in "relative" normalisation are splatted, blurred and
        # read by one compiled pass, their margins and costs by compiled loops (data_term_kernel): the same
        # costs bit for bit, batched and alone, with or without either floor, and with a model given twice
        # (each event's best value then comes from two models: the first is its owner, as torch's max).
        pytest.importorskip("numba")
        from evseg_torch.synthetic import make_scene

        windows, pools = _windows()
        signs = torch.Generator().manual_seed(3)
        windows = [
            EventBatch(w.xy, w.t, torch.randint(2, (len(w),), generator=signs) * 2.0 - 1) for w in windows
        ]
        params = torch.nn.utils.rnn.pad_sequence(pools, batch_first=True)
        valid = torch.tensor([[True, True, True], [True, True, False], [True, True, True]])
        scene = make_scene((45, 60), 0.03, 2, rng=0, n_events=3000)
        dense = to_torch(scene.events)
        kwargs = {"normalization": "relative", "polarity": True, "margin": margin, "sigma": 0.65}
        kwargs |= {"floor_quantile": floors[0], "pool_floor_quantile": floors[1]}

        def costs():
            found = [emsgc_cost(Translation((32, 40)), batch_windows(windows), params, valid=valid, **kwargs)]
            found += [
                emsgc_cost(Translation((32, 40)), w, p, **kwargs) for w, p in zip(windows, pools, strict=True)
            ]
            pool = torch.tensor(
                [
                    [100.0, -50.0, 1.0, -2.0],
                    [0.0, 0.0, 0.0, 0.0],
                    [-300.0, 20.0, 0.0, 5.0],
                    [0.0, 0.0, 0.0, 0.0],
                ]
            )
            return [*found, emsgc_cost(Affine4((45, 60)), dense, pool, **kwargs)]

        compiled = costs()
        with using_backend("torch"):
            for found, expected in zip(compiled, costs(), strict=True):
                assert torch.equal(found, expected)

    def test_compiled_images_keep_the_gradient(self):
        # With a gradient to keep, the tensor code runs: the costs stay differentiable in the parameters.
        windows, pools = _windows()
        params = pools[0].clone().requires_grad_()
        cost = emsgc_cost(Translation((32, 40)), windows[0], params, normalization="relative", polarity=True)
        cost.sum().backward()
        assert params.grad is not None and torch.isfinite(params.grad).all()

    def test_margins_differ(self):
        # The windows' own margins (margin=None) differ, so the batch above holds each window's IWEs in
        # its extent of a canvas of the widest margin.
        windows, pools = _windows()
        model = Translation((32, 40))
        margins = [
            _margins(
                _overshoots(
                    warp_events(model, w.xy, w.t, p)[None],
                    torch.ones(1, len(p), len(w), dtype=torch.bool),
                    32,
                    40,
                ).tolist(),
                32,
                40,
            )
            for w, p in zip(windows, pools, strict=True)
        ]
        assert len({margin for (margin,) in margins}) == 3, margins

    def test_module_and_exceptions(self):
        windows, pools = _windows()
        model = Translation((32, 40))
        batch = batch_windows(windows[:2])
        params = torch.nn.utils.rnn.pad_sequence(pools[:2], batch_first=True)
        torch.testing.assert_close(
            EmsgcCost(model, normalization="relative")(batch, params),
            emsgc_cost(model, batch, params, normalization="relative"),
        )
        with pytest.raises(ShapeError, match=r"\(B, K, 2\) with K >= 1 for the translation model and B = 2"):
            emsgc_cost(model, batch, params[0])
        with pytest.raises(ShapeError, match=r"valid must be \(B, K\)"):
            emsgc_cost(model, batch, params, valid=torch.ones(2, 2, dtype=torch.bool))
        with pytest.raises(ShapeError, match="valid"):
            emsgc_cost(model, windows[0], pools[0], valid=torch.ones(1, 3, dtype=torch.bool))


class TestDataCost:
    def test_cardinality_and_range(self):
        events = _edge_events()
        cost = emsgc_cost(Translation((32, 40)), events, torch.randn(5, 2) * 200)
        assert cost.shape == (400, 5)
        assert cost.min() >= 0 and cost.max() <= 255

    def test_matches_reference(self, dtype):
        events = _edge_events(dtype=dtype)
        model = Affine4((32, 40))
        params = torch.tensor(
            [[300.0, -100.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [250.0, -80.0, 2.0, -1.0]], dtype=dtype
        )
        expected = _reference(model, events, params, (32, 40), 1.0)
        torch.testing.assert_close(
            emsgc_cost(model, events, params, sigma=1.0), expected, atol=1e-3, rtol=1e-4
        )

    def test_true_model_is_cheapest(self):
        events = _edge_events()
        cost = emsgc_cost(
            Translation((32, 40)), events, torch.tensor([[300.0, -100.0], [0.0, 0.0], [-300.0, 0.0]])
        )
        mean = cost.mean(0)
        assert mean[0] < 0.6 * mean[1] and mean[0] < 0.6 * mean[2]
        assert (cost.argmin(1) == 0).float().mean() > 0.9

    def test_sharper_images_tell_a_nearby_model_apart(self):
        # Level two's data term blurs by data_sigma (0.7), not the refits' 1 px: a model 1.5 px off over the
        # window pays more under the sharper images (measured 19-23 cost units more per event at sigma 1,
        # 30-35 at 0.7 on five draws of these events).
        events = _edge_events()
        pool = torch.tensor([[300.0, -100.0], [375.0, -100.0]])  # 75 px/s over 20 ms: 1.5 px off

        def penalty(sigma):
            cost = emsgc_cost(Translation((32, 40)), events, pool, sigma=sigma, normalization="relative")
            return float((cost[:, 1] - cost[:, 0]).mean())

        assert penalty(0.7) > 1.3 * penalty(1.0) > 0
        segmenter = GraphCutContrastSegmenter("translation", (32, 40), data_sigma=0.5, sigma=1.5)
        assert segmenter.data_term.sigma == 0.5 and segmenter.refit.sigma == 1.5

    def test_joint_normalisation(self):
        # A sharp extra model raises the global maximum, so every other model's costs go up.
        events = _edge_events()
        model = Translation((32, 40))
        blurry = torch.tensor([[0.0, 0.0]])
        alone = emsgc_cost(model, events, blurry)
        together = emsgc_cost(model, events, torch.cat([blurry, torch.tensor([[300.0, -100.0]])]))
        assert alone.min() == 0  # the sharpest pixel of the pool costs nothing
        assert torch.all(together[:, 0] >= alone[:, 0] - 1e-4)
        assert together[:, 0].mean() > alone[:, 0].mean() + 10

    def test_relative_normalisation(self):
        # Each event's best model costs 0 where its value reaches the floor; a bright peak elsewhere
        # does not raise the other models' costs, unlike the global normalisation.
        events = _edge_events()
        model = Translation((32, 40))
        pool = torch.tensor([[300.0, -100.0], [0.0, 0.0], [-300.0, 0.0]])
        cost = emsgc_cost(model, events, pool, normalization="relative")
        assert cost.shape == (400, 3) and cost.min() >= 0 and cost.max() <= 255
        # Best values at or above the floor cost 0: at least the sharpest tenth of a model's own events.
        assert (cost.min(1).values == 0).float().mean() >= 0.09
        assert (cost.argmin(1) == 0).float().mean() > 0.9
        # The costs of a model do not depend on how sharp the pool's other images are elsewhere: only
        # each event's own best value (and the floor) counts; two copies of a model cost the same.
        duplicate = emsgc_cost(model, events, pool[[0, 0]], normalization="relative")
        torch.testing.assert_close(duplicate[:, 0], duplicate[:, 1])
        with pytest.raises(ConfigError, match="normalization"):
            emsgc_cost(model, events, pool, normalization="max")

    def test_own_floor_scales_each_layer_by_its_own_sharpness(self):
        # A sparse line beside a dense one, each moving on its own. With the pool's 90th percentile
        # alone as the floor (the floor before v0.4) the dense line sets it, and none of the
        # sparse line's events costs 0 under its own model; with each event's own floor, the sharpest
        # tenth of each line's events does.
        dense = _edge_events(count=1600, flow=(300.0, -100.0), size=(32, 80), seed=0)
        sparse = _edge_events(count=100, flow=(-200.0, 50.0), size=(32, 80), seed=1)
        xy = torch.cat([dense.xy, sparse.xy + torch.tensor([40.0, 0.0])])
        order = torch.argsort(torch.cat([dense.t, sparse.t]))
        events = EventBatch(xy[order], torch.cat([dense.t, sparse.t])[order], torch.ones(1700))
        layer = (order >= 1600).long()  # 0 dense, 1 sparse
        model, pool = Translation((32, 80)), torch.tensor([[300.0, -100.0], [-200.0, 50.0]])

        def costs(own, pool_floor):
            return emsgc_cost(
                model,
                events,
                pool,
                normalization="relative",
                floor_quantile=own,
                pool_floor_quantile=pool_floor,
            )

        pool_only, own_only, both = costs(None, 0.9), costs(0.9, None), costs(0.9, 0.75)
        own_cost = own_only.gather(1, layer[:, None])[:, 0]
        assert (pool_only[layer == 1, 1] == 0).sum() == 0
        for index in (0, 1):
            assert (own_cost[layer == index] == 0).float().mean() >= 0.09
        # A floor is a lower bound of each event's divisor: the larger of two floors costs at least as much.
        assert torch.all(both >= own_only - 1e-4) and torch.all(both >= costs(None, 0.75) - 1e-4)

    @pytest.mark.parametrize(
        "name, value", [("floor_quantile", 0.0), ("floor_quantile", 1.5), ("pool_floor_quantile", True)]
    )
    def test_floor_quantiles_are_checked(self, name, value):
        with pytest.raises(ConfigError, match=name):
            emsgc_cost(Translation((32, 40)), _edge_events(), torch.zeros(1, 2), **{name: value})
        with pytest.raises(ConfigError, match=name):
            EmsgcCost(Translation((32, 40)), **{name: value})

    @pytest.mark.parametrize("normalization", NORMALIZATIONS)
    def test_empty_window(self, normalization):
        events = EventBatch(torch.zeros(0, 2), torch.zeros(0), torch.zeros(0))
        cost = emsgc_cost(Translation((8, 8)), events, torch.zeros(2, 2), normalization=normalization)
        assert cost.shape == (0, 2)

    def test_single_pixel_is_free(self):
        events = EventBatch(torch.full((10, 2), 3.0), torch.linspace(0, 0.01, 10), torch.ones(10))
        cost = emsgc_cost(Translation((8, 8)), events, torch.zeros(1, 2))
        torch.testing.assert_close(cost, torch.zeros(10, 1))

    def test_outside_costs_255(self):
        events = EventBatch(torch.tensor([[1.0, 1.0], [5.0, 5.0]]), torch.tensor([0.01, 0.01]), torch.ones(2))
        cost = emsgc_cost(Translation((8, 8)), events, torch.tensor([[500.0, 0.0]]))  # 5 px to the left
        assert cost[0, 0] == 255.0 and cost[1, 0] < 255.0

    def test_margin_keeps_events_carried_out_of_the_sensor(self):
        events = EventBatch(
            torch.tensor([[1.0, 1.0], [20.0, 20.0]]), torch.tensor([0.01, 0.01]), torch.ones(2)
        )
        model = Translation((40, 40))
        left = torch.tensor([[500.0, 0.0]])  # 5 px to the left: the first event lands at x = -4
        assert emsgc_cost(model, events, left)[0, 0] == 255.0
        assert emsgc_cost(model, events, left, margin=4)[0, 0] == 0.0
        # The automatic margin is the overshoot, 4 px, capped at an eighth of the larger side, 5 px.
        torch.testing.assert_close(
            emsgc_cost(model, events, left, margin=None), emsgc_cost(model, events, left, margin=4)
        )
        assert emsgc_cost(model, events, left * 10, margin=None)[0, 0] == 255.0
        for margin in (-1, 1.5, True):
            with pytest.raises(ConfigError, match="margin"):
                emsgc_cost(model, events, left, margin=margin)

    def test_polarity(self):
        model = Translation((32, 40))
        pool = torch.tensor([[0.0, 0.0], [300.0, -100.0]])
        line = _edge_events()
        for normalization in NORMALIZATIONS:  # events of one polarity make one image, as without
            torch.testing.assert_close(
                emsgc_cost(model, line, pool, normalization=normalization, polarity=True),
                emsgc_cost(model, line, pool, normalization=normalization),
            )
        # A still edge of positive events and a few negative events on it: an event of the other sign
        # lands on a bright pixel of the image of all events but on a dark one of its own polarity's.
        rows = torch.arange(4.0, 28.0)
        edge = torch.stack([torch.full_like(rows, 10.0), rows], 1).repeat(5, 1)
        probes = torch.tensor([[10.0, 8.0], [10.0, 16.0], [10.0, 24.0]])
        events = EventBatch(
            torch.cat([edge, probes]),
            torch.linspace(0, 0.02, len(edge) + 3),
            torch.cat([torch.ones(len(edge)), -torch.ones(3)]),
        )
        mixed = emsgc_cost(model, events, pool[:1])
        split = emsgc_cost(model, events, pool[:1], polarity=True)
        assert mixed[-3:].max() < 10 and split[-3:].min() > 200

    def test_gradcheck(self):
        events = _edge_events(count=30, size=(12, 14), dtype=torch.float64)
        events = EventBatch(events.xy.clamp(0, 10), events.t, events.p)
        params = torch.tensor([[30.0, -10.0], [5.0, 7.0]], dtype=torch.float64, requires_grad=True)
        model = Translation((12, 14))
        assert torch.autograd.gradcheck(lambda p: emsgc_cost(model, events, p), (params,), fast_mode=True)

    def test_module(self):
        events = _edge_events()
        model = Translation((32, 40))
        params = torch.randn(3, 2) * 100
        torch.testing.assert_close(
            EmsgcCost(model, sigma=1.0)(events, params), emsgc_cost(model, events, params)
        )
        assert "sigma=1.0" in repr(EmsgcCost(model))
        torch.testing.assert_close(
            EmsgcCost(model, normalization="relative")(events, params),
            emsgc_cost(model, events, params, normalization="relative"),
        )
        module = EmsgcCost(model, normalization="relative", polarity=True, margin=None)
        torch.testing.assert_close(
            module(events, params),
            emsgc_cost(model, events, params, normalization="relative", polarity=True, margin=None),
        )
        assert "polarity=True, margin=None" in repr(module)

    def test_device(self, device):
        events = _edge_events()
        params = torch.tensor([[300.0, -100.0], [0.0, 0.0]])
        expected = emsgc_cost(Translation((32, 40)), events, params)
        cost = emsgc_cost(Translation((32, 40)), events.to(device), params.to(device))
        assert cost.device.type == device.type
        torch.testing.assert_close(cost.cpu(), expected, atol=1e-3, rtol=1e-4)

    def test_exceptions(self):
        events = _edge_events()
        with pytest.raises(ShapeError, match=r"\(K, 2\)"):
            emsgc_cost(Translation((32, 40)), events, torch.zeros(2))
        with pytest.raises(ShapeError, match=r"\(K, 4\)"):
            emsgc_cost(Affine4((32, 40)), events, torch.zeros(2, 2))
        with pytest.raises(ShapeError, match="K >= 1"):
            emsgc_cost(Translation((32, 40)), events, torch.zeros(0, 2))
        with pytest.raises(ModelError, match="params hold NaN or inf"):
            emsgc_cost(Translation((32, 40)), events, torch.tensor([[0.0, float("nan")]]))
        with pytest.raises(ShapeError, match="images must be"):
            sample_bilinear(torch.zeros(2, 3, 3), torch.zeros(1, 4, 2))


@pytest.mark.parametrize("q", [0.25, 0.75, 0.9, 1.0])
def test_quantile_selections_agree(q):
    # The CPU's selection (NumPy's partition of each row's selected values) and the one for other devices
    # (one kthvalue over rows padded with infinities) pick the same element: the rank-th smallest.
    generator = torch.Generator().manual_seed(0)
    values = torch.rand(5, 300, generator=generator)
    share = torch.tensor([0.0, 0.01, 0.3, 0.9, 1.0])[:, None]
    selected = torch.rand(5, 300, generator=generator) < share
    counts = selected.sum(dim=1)
    ranks = (counts.double() * q).round().clamp_min(1).long()
    by_partition = _select_by_partition(values, selected, ranks, counts)
    assert torch.equal(by_partition, _select_by_kthvalue(values, selected, ranks, counts))
    for row in range(5):
        chosen = values[row][selected[row]].sort().values
        expected = chosen[ranks[row] - 1] if len(chosen) else torch.finfo(values.dtype).tiny
        assert by_partition[row] == expected
