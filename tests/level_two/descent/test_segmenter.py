import time

import numpy as np
import pytest
import torch

from evseg_torch.errors import ConfigError, EventFormatError, ModelError, ShapeError
from evseg_torch.evaluation.metrics import labelling_accuracy, per_object_iou
from evseg_torch.events import EventBatch, batch_windows, to_torch
from evseg_torch.graphcut.problem import labeling_energy
from evseg_torch.level_two.descent import segmenter as segmenter_module
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter, LevelTwoResult
from evseg_torch.level_two.discovery import Discovery
from evseg_torch.level_two.energy.graph import event_graph, site_graph
from evseg_torch.level_two.energy.label_cost import label_cost
from evseg_torch.motion import Translation
from evseg_torch.synthetic import make_scene


def _two_layer_events(seed=0, size=(60, 80), count=(3000, 1500)):
    """Random dots moving with two translations: a background and a square object in front of it."""
    rng = np.random.default_rng(seed)
    height, width = size
    flows = np.array([[250.0, 80.0], [-220.0, 150.0]])
    regions = [(0, width, 0, height), (25, 50, 20, 40)]
    xy, t, labels = [], [], []
    for layer, (n_events, (x0, x1, y0, y1)) in enumerate(zip(count, regions, strict=True)):
        dots = np.column_stack([rng.uniform(x0, x1, 150), rng.uniform(y0, y1, 150)])
        times = rng.uniform(0, 0.02, n_events)
        xy.append(dots[rng.integers(0, 150, n_events)] + times[:, None] * flows[layer])
        t.append(times)
        labels.append(np.full(n_events, layer))
    xy, t, labels = np.round(np.concatenate(xy)), np.concatenate(t), np.concatenate(labels)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)
    # The object occludes the background: no background event inside the object's moving square.
    x0, x1, y0, y1 = regions[1]
    back = xy - t[:, None] * flows[1]
    inside &= (labels == 1) | ~(
        (back[:, 0] >= x0 - 1) & (back[:, 0] <= x1 + 1) & (back[:, 1] >= y0 - 1) & (back[:, 1] <= y1 + 1)
    )
    order = np.argsort(t[inside], kind="stable")
    xy, t, labels = xy[inside][order], t[inside][order], labels[inside][order]
    events = EventBatch(
        torch.as_tensor(xy, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32), torch.ones(len(t))
    )
    return events, labels, flows


def _pool(flows, seed=0):
    """The true flows perturbed by about a pixel over the window, plus two spurious models."""
    rng = np.random.default_rng(seed)
    spurious = np.array([[-300.0, -300.0], [0.0, 0.0]])
    return torch.as_tensor(
        np.concatenate([flows + rng.normal(0, 50, flows.shape), spurious]), dtype=torch.float32
    )


@pytest.fixture(scope="module")
def two_layers():
    return _two_layer_events()


def _segmenter(**kwargs):
    kwargs = {"lambda_label": 2000.0, "max_iter": 10, **kwargs}
    return GraphCutContrastSegmenter(Translation((60, 80)), (60, 80), **kwargs)


class TestGraphCutContrastSegmenter:
    def test_segments_two_layers(self, two_layers):
        events, labels, flows = two_layers
        result = _segmenter()(events, _pool(flows))
        assert isinstance(result, LevelTwoResult)
        assert result.params.shape == (2, 2)  # the spurious models are gone
        assert labelling_accuracy(result.labels.numpy(), labels) > 0.95
        assert per_object_iou(result.labels.numpy(), labels)[1] > 0.9
        # The refits move the perturbed models back towards the truth; cluster 0 is the background.
        torch.testing.assert_close(
            result.params, torch.as_tensor(flows, dtype=torch.float32), atol=25.0, rtol=0
        )

    def test_cardinality_and_bookkeeping(self, two_layers):
        events, _, flows = two_layers
        result = _segmenter()(events, _pool(flows))
        n_clusters = result.params.shape[0]
        assert result.labels.dtype == torch.int64 and result.labels.shape == (len(events),)
        assert result.iwes.shape == (n_clusters, 60, 80)
        sizes = torch.bincount(result.labels, minlength=n_clusters)
        assert torch.all(sizes > 0) and torch.all(sizes[:-1] >= sizes[1:])  # renumbered by size
        # Each cluster's image holds its own events (sigma = 0 voting keeps the count, bar the border).
        assert torch.all(result.iwes.sum((1, 2)) <= sizes + 1e-3)
        assert torch.all(result.iwes.sum((1, 2)) > 0.9 * sizes)
        assert 1 <= len(result.energy_history) <= 5
        assert set(result.timings_ms) == {"graph", "data_term", "labelling", "refit", "discovery", "images"}

    def test_labelling_never_raises_the_energy(self, two_layers):
        events, _, flows = two_layers
        pool = _pool(flows)
        # Without discovery, so that the returned labels come from the one labelling with the pool.
        segmenter = _segmenter(n_iter_segmentation=1, discovery_rounds=0)
        result = segmenter(events, pool)
        cost = segmenter.data_term(events, pool).double().numpy()
        edges, weights = event_graph(events)
        energy = {
            "smoothness": segmenter.config.lambda_smooth,
            "label_cost": label_cost(
                len(events), segmenter.config.lambda_label, segmenter.config.label_cost_events
            ),
        }
        initial = labeling_energy(cost.argmin(1), cost, edges, weights, **energy)
        assert result.energy_history[0] <= initial
        # The reported energy is the energy of the returned labels under the initial models.
        mapping = [int(np.argmin(np.abs(pool.numpy() - p.numpy()).sum(1))) for p in result.params]
        assert labeling_energy(
            np.asarray(mapping)[result.labels.numpy()], cost, edges, weights, **energy
        ) == (pytest.approx(result.energy_history[0]))
        # From the result's own labels, one more labelling with the surviving models cannot do worse than
        # those labels under the same models' costs (which depend on the whole pool).
        survivors = pool[mapping]
        again = segmenter(events, survivors, init_labels=result.labels)
        cost = segmenter.data_term(events, survivors)
        before = labeling_energy(result.labels.numpy(), cost.double().numpy(), edges, weights, **energy)
        # The segmenter sums each site's event costs in float32, this test in float64: equal up to that
        # rounding (1.4e-4 of 2.2e5 seen), not bit for bit.
        assert again.energy_history[0] <= before * (1 + 1e-6)

    def test_list_input_matches_single_calls(self, two_layers):
        events, _, flows = two_layers
        other, _, other_flows = _two_layer_events(seed=1)
        segmenter = _segmenter(n_iter_segmentation=2)
        batch = segmenter([events, other], [_pool(flows), _pool(other_flows)])
        for result, single in zip(
            batch, [segmenter(events, _pool(flows)), segmenter(other, _pool(other_flows))], strict=True
        ):
            torch.testing.assert_close(result.labels, single.labels)
            torch.testing.assert_close(result.params, single.params)
            assert result.energy_history == single.energy_history
        shared = segmenter([events, events], _pool(flows))
        torch.testing.assert_close(shared[0].labels, shared[1].labels)
        # A padded batch with one pool per window, (B, K, P), gives the list's results.
        padded = segmenter(batch_windows([events, other]), torch.stack([_pool(flows), _pool(other_flows)]))
        assert isinstance(padded, list) and len(padded) == 2
        for result, listed in zip(padded, batch, strict=True):
            torch.testing.assert_close(result.labels, listed.labels)
            torch.testing.assert_close(result.params, listed.params)
            torch.testing.assert_close(result.soft_assignments, listed.soft_assignments)
            assert result.energy_history == listed.energy_history

    def test_padded_batch_with_initial_labels(self, two_layers):
        events, labels, flows = two_layers
        fewer = EventBatch(events.xy[:1500], events.t[:1500], events.p[:1500])
        segmenter = _segmenter(n_iter_segmentation=1, discovery_rounds=0)
        init = [torch.as_tensor(labels), torch.as_tensor(labels[:1500])]
        listed = segmenter([events, fewer], _pool(flows), init)
        padded_labels = torch.full((2, len(events)), 99)  # padding holds labels no model has
        padded_labels[0], padded_labels[1, :1500] = init
        padded = segmenter(batch_windows([events, fewer]), _pool(flows), padded_labels)
        for result, single in zip(padded, listed, strict=True):
            torch.testing.assert_close(result.labels, single.labels)
            torch.testing.assert_close(result.params, single.params)
        with pytest.raises(ShapeError, match=r"\(B, N_max\)"):
            segmenter(batch_windows([events, fewer]), _pool(flows), padded_labels[:, :10])
        with pytest.raises(ShapeError, match="2 windows but 3 pools"):
            segmenter(batch_windows([events, fewer]), _pool(flows).expand(3, -1, -1))

    def test_soft_assignments_reuse_the_last_data_cost(self, two_layers):
        events, _, flows = two_layers
        segmenter = _segmenter(soft_temperature=40.0)
        calls = []
        data_term = segmenter.data_term.forward

        def recorded(events, params, valid=None):
            cost = data_term(events, params, valid)
            calls.append((params[0].clone(), cost[0]))  # a batch of the one window
            return cost

        segmenter.data_term.forward = recorded
        result = segmenter(events, _pool(flows))
        soft = result.soft_assignments
        assert soft.shape == (len(events), result.params.shape[0]) and soft.dtype == events.xy.dtype
        torch.testing.assert_close(soft.sum(dim=1), torch.ones(len(events)))
        # One data-term pass per labelling, none more; the last labelling's pool holds the final models
        # (here with the discovery proposals it rejected), and its costs give the soft assignments.
        assert len(calls) == len(result.energy_history)
        pool, cost = calls[-1]
        keep = [int(torch.nonzero((pool == row).all(dim=1))[0, 0]) for row in result.params]
        torch.testing.assert_close(soft, torch.softmax(-cost[:, keep] / 40.0, dim=1))

    def test_single_cluster_stops(self, two_layers):
        events, _, flows = two_layers
        result = _segmenter(lambda_label=1e7, discovery_rounds=0)(events, _pool(flows))
        assert result.params.shape[0] == 1 and len(result.energy_history) == 1
        # Discovery still tries to split the last cluster, and the label cost rejects the proposals.
        result = _segmenter(lambda_label=1e7)(events, _pool(flows))
        assert result.params.shape[0] == 1 and len(result.energy_history) <= 2
        assert torch.all(result.labels == 0)

    def test_does_not_mutate(self, two_layers):
        events, _, flows = two_layers
        pool = _pool(flows)
        copies = pool.clone(), events.xy.clone()
        _segmenter(n_iter_segmentation=2)(events, pool)
        torch.testing.assert_close(pool, copies[0])
        torch.testing.assert_close(events.xy, copies[1])

    def test_device(self, device, two_layers):
        events, labels, flows = two_layers
        result = _segmenter()(events.to(device), _pool(flows).to(device))
        assert result.labels.device.type == device.type and result.params.device.type == device.type
        assert labelling_accuracy(result.labels.cpu().numpy(), labels) > 0.95
        assert result.soft_assignments.device.type == device.type
        torch.testing.assert_close(result.soft_assignments.sum(dim=1).cpu(), torch.ones(len(events)))

    def test_learning_through_contrast_loss(self, two_layers):
        # A tiny network predicts both layers' flows from a fixed input; trained through the contrast loss.
        events, labels, flows = two_layers
        torch.manual_seed(0)
        net = torch.nn.Linear(4, 4)
        feature = torch.ones(1, 4)
        segmenter = _segmenter()
        optimiser = torch.optim.Adam(net.parameters(), lr=0.05)
        target = torch.as_tensor(labels)
        losses = []
        for _ in range(60):
            optimiser.zero_grad()
            params = 100.0 * net(feature).view(2, 2) + torch.as_tensor(flows, dtype=torch.float32) * 0.6
            loss = segmenter.contrast_loss(events, params, target).sum()
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        assert losses[-1] < losses[0] - 0.1 * abs(losses[0])
        assert segmenter.contrast_loss(events, torch.zeros(3, 2)).shape == (3,)

    def test_refit_subsample_and_label_tol(self, two_layers):
        # Refits on 500 events per cluster and a loose stopping rule still recover both layers. Where one
        # refit from 500 events lands depends on which events it draws and, as L-BFGS on so few events
        # is chaotic, on the last bits of its start: from four perturbed pools the worst flow error
        # spreads over 15-80 px/s (either solver, torch's or ours), so the median is what is asserted.
        events, labels, flows = two_layers
        errors = []
        for seed in range(4):
            result = _segmenter(refit_max_events=500, label_tol=0.05, site_time_slices=None)(
                events, _pool(flows, seed)
            )
            assert result.params.shape == (2, 2)
            assert labelling_accuracy(result.labels.numpy(), labels) > 0.95
            errors.append(float((result.params - torch.as_tensor(flows, dtype=torch.float32)).abs().max()))
        assert np.median(errors) < 40.0  # px/s: 0.8 px over the 20 ms window
        exact = _segmenter(refit_max_events=None, label_tol=0.0, data_normalization="global")(
            events, _pool(flows)
        )
        assert labelling_accuracy(exact.labels.numpy(), labels) > 0.95

    def test_module_repr_and_names(self):
        segmenter = GraphCutContrastSegmenter("affine4", (20, 30), lambda_smooth=40.0)
        assert segmenter.model.name == "affine4"
        assert "lambda_smooth=40.0" in repr(segmenter)

    def test_exceptions(self, two_layers):
        events, _, flows = two_layers
        segmenter = _segmenter()
        with pytest.raises(EventFormatError, match="EventBatch"):
            segmenter(np.zeros((10, 4)), _pool(flows))
        with pytest.raises(EventFormatError, match="0 events"):
            segmenter(EventBatch(torch.zeros(0, 2), torch.zeros(0), torch.zeros(0)), _pool(flows))
        with pytest.raises(ShapeError, match=r"\(K, 2\)"):
            segmenter(events, torch.zeros(3, 4))
        with pytest.raises(ShapeError, match="K >= 1"):
            segmenter(events, torch.zeros(0, 2))
        with pytest.raises(ModelError, match="NaN"):
            segmenter(events, torch.full((2, 2), float("nan")))
        with pytest.raises(ShapeError, match=r"torch\.Tensor"):
            segmenter(events, np.zeros((2, 2)))
        with pytest.raises(ShapeError, match=r"lie in \[0, 4\)"):
            segmenter(events, _pool(flows), init_labels=np.full(len(events), 7))
        with pytest.raises(ShapeError, match="integers of shape"):
            segmenter(events, _pool(flows), init_labels=np.zeros(3, dtype=np.int64))
        with pytest.raises(ShapeError, match="2 windows"):
            segmenter([events, events], [_pool(flows)])
        with pytest.raises(ConfigError, match="lambda_smooth"):
            GraphCutContrastSegmenter("translation", (10, 10), lambda_smooth=-1.0)
        with pytest.raises(ConfigError, match="n_iter_labeling"):
            GraphCutContrastSegmenter("translation", (10, 10), n_iter_labeling=0)
        with pytest.raises(ConfigError, match="data_normalization"):
            GraphCutContrastSegmenter("translation", (10, 10), data_normalization="max")
        with pytest.raises(ConfigError, match="refit_max_events"):
            GraphCutContrastSegmenter("translation", (10, 10), refit_max_events=0)
        with pytest.raises(ConfigError, match="label_tol"):
            GraphCutContrastSegmenter("translation", (10, 10), label_tol=1.0)
        with pytest.raises(ConfigError, match="site_time_slices"):
            GraphCutContrastSegmenter("translation", (10, 10), site_time_slices=0)
        with pytest.raises(ConfigError, match="warm_max_iter"):
            GraphCutContrastSegmenter("translation", (10, 10), warm_max_iter=0)
        for temperature in (0.0, -1.0, float("nan"), float("inf")):
            with pytest.raises(ConfigError, match=r"'level_two\.soft_temperature' has invalid value"):
                GraphCutContrastSegmenter("translation", (10, 10), soft_temperature=temperature)
        for name in ("max_iter", "n_iter_segmentation", "discovery_max_iter"):
            with pytest.raises(
                ConfigError, match=f"'level_two.{name}' has invalid value True: expected an integer"
            ):
                GraphCutContrastSegmenter("translation", (10, 10), **{name: True})
        with pytest.raises(ConfigError, match=r"unknown config key level_two\.'lambda_smoth'"):
            GraphCutContrastSegmenter("translation", (10, 10), lambda_smoth=1.0)

    @pytest.mark.parametrize("site_time_slices", [1, 3])
    def test_sites_share_labels(self, two_layers, site_time_slices):
        events, labels, flows = two_layers
        segmenter = _segmenter(site_time_slices=site_time_slices, n_iter_segmentation=2)
        result = segmenter(events, _pool(flows))
        assert labelling_accuracy(result.labels.numpy(), labels) > 0.95
        sites, _, _ = site_graph(events, time_slices=site_time_slices)
        per_site = np.zeros((sites.max() + 1, result.params.shape[0]), dtype=int)
        np.add.at(per_site, (sites, result.labels.numpy()), 1)
        assert ((per_site > 0).sum(1) == 1).all()
        # Initial labels that differ within a site start from each site's majority.
        noisy = result.labels.clone()
        noisy[::7] = (noisy[::7] + 1) % result.params.shape[0]
        again = segmenter(events, result.params, init_labels=noisy)
        assert labelling_accuracy(again.labels.numpy(), labels) > 0.95


BATCH_SIZE = (90, 120)


@pytest.fixture(scope="module")
def batch_scenes():
    """Four windows of 1-3 objects (1.8k-4.1k events), each with its true models perturbed by about a pixel
    of displacement plus a spurious model (pools of 3-5 models)."""
    windows, pools = [], []
    for seed in range(4):
        scene = make_scene(BATCH_SIZE, 0.03, n_objects=1 + seed % 3, rng=seed)
        model = scene.motions[0].model
        truth = np.stack([motion.params for motion in scene.motions])
        rng = np.random.default_rng(100 + seed)
        init = truth + rng.normal(0, 1.0, truth.shape) / model.displacement_scale(0.03)
        spurious = rng.normal(0, 1, (1, truth.shape[1])) * np.array([600.0, 600.0, 3.0, 3.0])
        windows.append(to_torch(scene.events))
        pools.append(torch.as_tensor(np.concatenate([init, spurious]), dtype=torch.float32))
    return model, windows, pools


class TestBatches:
    def test_batch_equals_one_by_one(self, device, batch_scenes):
        # The windows of a list or of a padded batch are segmented together, and each gets the result it
        # gets alone: on the CPU bit for bit (labels, models, energies, soft assignments and images).
        # CUDA's scatter-adds and reductions round differently in a batch, and the descent can amplify
        # that, so there the first labelling only is compared.
        model, windows, pools = batch_scenes
        windows = [window.to(device) for window in windows]
        pools = [pool.to(device) for pool in pools]
        kwargs = {} if device.type == "cpu" else {"n_iter_segmentation": 1, "discovery_rounds": 0}
        segmenter = GraphCutContrastSegmenter(model, BATCH_SIZE, **kwargs)
        alone = [segmenter(window, pool) for window, pool in zip(windows, pools, strict=True)]
        listed = segmenter(windows, pools)
        padded = segmenter(batch_windows(windows), pools)
        assert len(listed) == len(padded) == 4
        for single, *batched in zip(alone, listed, padded, strict=True):
            for result in batched:
                assert torch.equal(result.labels, single.labels)
                assert result.labels.device.type == device.type
                if device.type == "cpu":
                    assert result.energy_history == single.energy_history
                    for name in ("params", "soft_assignments", "iwes"):
                        assert torch.equal(getattr(result, name), getattr(single, name)), name
                else:
                    torch.testing.assert_close(result.params, single.params)
                    torch.testing.assert_close(result.soft_assignments, single.soft_assignments)
        # How many rounds each window takes depends on floating-point paths that differ between CPUs, so
        # only what the lockstep guarantees is asserted: each window stops on its own (its rounds equal its
        # solo run's, compared above through the energy histories on the CPU), within the configured rounds.
        # The object phase adds one labelling with the support term and one per split.
        objects = segmenter.config.objects * (1 + segmenter.config.object_splits)
        limit = segmenter.config.n_iter_segmentation + segmenter.config.discovery_rounds * 2 + objects
        assert all(1 <= len(result.energy_history) <= limit for result in listed)

    def test_discovery_rounds_per_window(self, batch_scenes):
        # Each window of a batch may have its own discovery rounds (the pipeline gives a window that carries
        # models in fewer), and gets what a segmenter configured with them gives it alone.
        model, windows, pools = batch_scenes
        rounds = [0, 2, 1, 2]
        batched = GraphCutContrastSegmenter(model, BATCH_SIZE)(windows, pools, discovery_rounds=rounds)
        for window, pool, n_rounds, result in zip(windows, pools, rounds, batched, strict=True):
            alone = GraphCutContrastSegmenter(model, BATCH_SIZE, discovery_rounds=n_rounds)(window, pool)
            assert torch.equal(result.labels, alone.labels) and torch.equal(result.params, alone.params)
            assert result.energy_history == alone.energy_history
        segmenter = GraphCutContrastSegmenter(model, BATCH_SIZE, discovery_rounds=0)
        overridden = segmenter(windows[1], pools[1], discovery_rounds=2)  # one window, the call's rounds
        assert torch.equal(overridden.labels, batched[1].labels)
        assert overridden.energy_history == batched[1].energy_history
        with pytest.raises(ShapeError, match="discovery_rounds"):
            segmenter(windows, pools, discovery_rounds=[1, 1])
        for bad in (-1, True, 1.5):
            with pytest.raises(ConfigError, match="discovery_rounds"):
                segmenter(windows[0], pools[0], discovery_rounds=bad)

    def test_carried_windows(self, batch_scenes):
        # A window that carries models in (a stream's) takes its own, shorter descent; in a batch each
        # window gets what it gets alone, carried or not, and a cold window is unchanged by the settings.
        model, windows, pools = batch_scenes
        carried = [True, False, True, False]
        settings = {"carried_rounds": 1, "carried_discovery": "new"}
        segmenter = GraphCutContrastSegmenter(model, BATCH_SIZE, **settings)
        batched = segmenter(windows, pools, carried=carried)
        plain = GraphCutContrastSegmenter(model, BATCH_SIZE)
        for window, pool, carries, result in zip(windows, pools, carried, batched, strict=True):
            alone = segmenter(window, pool, carried=carries)
            assert torch.equal(result.labels, alone.labels) and torch.equal(result.params, alone.params)
            assert result.energy_history == alone.energy_history
            if not carries:
                assert result.energy_history == plain(window, pool).energy_history
        # With one round, no discovery and no object phase, a carried window is labelled once.
        once = GraphCutContrastSegmenter(
            model, BATCH_SIZE, carried_rounds=1, discovery_rounds=0, objects=False
        )
        assert all(len(result.energy_history) == 1 for result in once(windows, pools, carried=True))
        with pytest.raises(ShapeError, match="carried"):
            segmenter(windows, pools, carried=[True])

    def test_groups_and_chunks_on_the_cpu(self, batch_scenes, monkeypatch):
        # On the CPU a large batch is segmented in groups of windows, and its data terms are computed in
        # chunks: the results are the same.
        model, windows, pools = batch_scenes
        segmenter = GraphCutContrastSegmenter(model, BATCH_SIZE, n_iter_segmentation=2)
        together = segmenter(windows, pools)
        monkeypatch.setattr(segmenter_module, "_CPU_BATCH_EVENTS", 6000)
        monkeypatch.setattr(segmenter_module, "_CPU_DATA_TERM_PAIRS", 10000)
        grouped = segmenter(windows, pools)
        for result, alone in zip(grouped, together, strict=True):
            assert torch.equal(result.labels, alone.labels) and torch.equal(result.params, alone.params)
            assert result.energy_history == alone.energy_history

    def test_timings_are_shared(self, batch_scenes):
        model, windows, pools = batch_scenes
        segmenter = GraphCutContrastSegmenter(model, BATCH_SIZE, n_iter_segmentation=2)
        start = time.perf_counter()
        results = segmenter(windows[:2], pools[:2])
        elapsed = 1e3 * (time.perf_counter() - start)
        total = sum(sum(result.timings_ms.values()) for result in results)
        stages = {"graph", "data_term", "labelling", "refit", "discovery", "images"}
        assert all(set(result.timings_ms) == stages for result in results)
        assert 0.8 * elapsed <= total <= elapsed

    def test_empty_list(self, batch_scenes):
        model, _, pools = batch_scenes
        assert GraphCutContrastSegmenter(model, BATCH_SIZE)([], pools[0]) == []


DISCOVERY_SIZE = (90, 120)
DISCOVERY_SEEDS = range(8)


def _missing_motion_window(seed):
    """A small two-object scene and a pool that lacks the motion of its larger object."""
    scene = make_scene(DISCOVERY_SIZE, 0.03, n_objects=2, rng=seed)
    events = to_torch(scene.events, t_ref_us=int(scene.events["t"][0]))
    counts = np.bincount(scene.labels[scene.labels >= 0], minlength=3)
    dropped = 1 + int(np.argmax(counts[1:]))
    truth = np.stack([motion.params for motion in scene.motions])
    pool = torch.as_tensor(np.delete(truth, dropped, axis=0), dtype=torch.float32)
    return scene, events, dropped, pool


@pytest.fixture(scope="module")
def missing_motion():
    """Per seed: the scene, the dropped layer, the pool and the results without and with discovery."""
    runs = []
    for seed in DISCOVERY_SEEDS:
        scene, events, dropped, pool = _missing_motion_window(seed)
        model = scene.motions[0].model
        results = {
            rounds: GraphCutContrastSegmenter(model, DISCOVERY_SIZE, discovery_rounds=rounds)(events, pool)
            for rounds in (0, 1)
        }
        runs.append((scene, dropped, pool, results))
    return runs


class TestDiscovery:
    def test_recovers_a_missing_motion(self, missing_motion):
        # Measured on seeds 0-7: mean IoU of the dropped object 0.35 without discovery, 0.58 with; a
        # cluster is added on 4 seeds; discovery never lowers the IoU.
        ious = np.array(
            [
                [per_object_iou(results[r].labels.numpy(), scene.labels)[dropped] for r in (0, 1)]
                for scene, dropped, _, results in missing_motion
            ]
        )
        without, with_discovery = ious.mean(axis=0)
        assert with_discovery >= 0.5, ious
        assert with_discovery - without >= 0.15, ious
        assert np.all(ious[:, 1] >= ious[:, 0] - 0.05), ious
        added = [results[1].params.shape[0] > results[0].params.shape[0] for *_, results in missing_motion]
        assert sum(added) >= 3, added

    def test_background_main_region_is_fitted_only_when_a_start_is_sharper(self, monkeypatch):
        # Seed 4: the missing object sits in the largest cluster, whose main group's start is sharper than
        # that cluster's model (the proposal finds the object); from the true models it is not, and that
        # fit, which would only return to the background's model, is skipped.
        proposed = []
        original = Discovery._proposal_starts

        def spy(self, state, regions):
            candidate, kept = original(self, state, regions)
            main = max((members for cluster, members in regions if cluster == 0), key=len, default=None)
            proposed.append(main is not None and any(members is main for _, members in kept))
            assert len(candidate.start) == len(kept)
            return candidate, kept

        monkeypatch.setattr(Discovery, "_proposal_starts", spy)
        scene, events, _, pool = _missing_motion_window(4)
        truth = torch.as_tensor(np.stack([motion.params for motion in scene.motions]), dtype=torch.float32)
        segmenter = GraphCutContrastSegmenter(scene.motions[0].model, DISCOVERY_SIZE, discovery_rounds=1)
        for start, fitted in ((pool, True), (truth, False)):
            proposed.clear()
            segmenter(events, start)
            assert proposed == [fitted]

    def test_no_discovery_only_removes_models(self, missing_motion):
        # The paper's level two (no discovery, no object phase, whose splits add clusters): the pool only
        # shrinks, in at most n_iter_segmentation labellings.
        for seed in DISCOVERY_SEEDS[:3]:
            scene, events, _, pool = _missing_motion_window(seed)
            segmenter = GraphCutContrastSegmenter(
                scene.motions[0].model, DISCOVERY_SIZE, discovery_rounds=0, objects=False
            )
            paper = segmenter(events, pool)
            assert paper.params.shape[0] <= pool.shape[0]
            assert len(paper.energy_history) <= segmenter.config.n_iter_segmentation
        for *_, results in missing_motion:
            assert results[0].timings_ms["discovery"] == 0.0
        assert any(results[1].params.shape[0] > pool.shape[0] for _, _, pool, results in missing_motion)

    def test_energy_history_and_labels(self, device):
        scene, events, _, pool = _missing_motion_window(0)
        segmenter = GraphCutContrastSegmenter(scene.motions[0].model, DISCOVERY_SIZE, discovery_rounds=1)
        result = segmenter(events.to(device), pool.to(device))
        n_clusters = result.params.shape[0]
        assert len(result.energy_history) >= 2 and all(np.isfinite(result.energy_history))
        assert result.labels.device.type == device.type and torch.isfinite(result.params).all()
        sizes = torch.bincount(result.labels, minlength=n_clusters)
        assert result.labels.min() >= 0 and len(sizes) == n_clusters  # labels index the params
        assert torch.all(sizes > 0) and torch.all(sizes[:-1] >= sizes[1:])  # renumbered by size
        assert result.iwes.shape == (n_clusters, *DISCOVERY_SIZE)

    def test_soft_assignments_agree_with_labels(self):
        # Measured 0.83 of the events with the data term's sigma of 1, 0.79 with 0.7 (the argmax ignores
        # the Potts term, which decides the rest; over the ten scenes of docs/level_two.md's calibration
        # the mean is 0.81 with either).
        scene = make_scene(DISCOVERY_SIZE, 0.03, n_objects=1, rng=0)
        model = scene.motions[0].model
        truth = np.stack([motion.params for motion in scene.motions])
        rng = np.random.default_rng(100)
        pool = truth + rng.normal(0, 1.0, truth.shape) / model.displacement_scale(0.03)
        segmenter = GraphCutContrastSegmenter(model, DISCOVERY_SIZE)
        result = segmenter(to_torch(scene.events), torch.as_tensor(pool, dtype=torch.float32))
        soft = result.soft_assignments
        assert soft.shape == (len(scene.events), result.params.shape[0]) == (len(scene.events), 2)
        torch.testing.assert_close(soft.sum(dim=1), torch.ones(len(scene.events)))
        assert (soft.argmax(dim=1) == result.labels).float().mean() >= 0.75
        assert "soft_temperature=20.0" in repr(segmenter)

    def test_label_cost_scales_with_the_window(self, two_layers):
        segmenter = _segmenter(lambda_label=3000.0, label_cost_events=5000.0)
        assert label_cost(
            5000, segmenter.config.lambda_label, segmenter.config.label_cost_events
        ) == pytest.approx(3000.0)
        assert label_cost(
            1250, segmenter.config.lambda_label, segmenter.config.label_cost_events
        ) == pytest.approx(3000.0)  # sparse windows keep lambda_label
        assert label_cost(
            20000, segmenter.config.lambda_label, segmenter.config.label_cost_events
        ) == pytest.approx(12000.0)
        fixed = _segmenter(lambda_label=3000.0, label_cost_events=None)
        assert (
            label_cost(1250, fixed.config.lambda_label, fixed.config.label_cost_events)
            == label_cost(20000, fixed.config.lambda_label, fixed.config.label_cost_events)
            == 3000.0
        )
        # The labelling pays the scaled cost: its energy is the returned labels' energy with it.
        events, _, flows = two_layers
        pool = _pool(flows)
        segmenter = _segmenter(n_iter_segmentation=1, discovery_rounds=0, label_cost_events=5000.0)
        result = segmenter(events, pool)
        cost = segmenter.data_term(events, pool).double().numpy()
        edges, weights = event_graph(events)
        mapping = [int(np.argmin(np.abs(pool.numpy() - p.numpy()).sum(1))) for p in result.params]
        labels = np.asarray(mapping)[result.labels.numpy()]
        energy = labeling_energy(
            labels,
            cost,
            edges,
            weights,
            smoothness=segmenter.config.lambda_smooth,
            label_cost=2000.0 * max(1.0, len(events) / 5000),
        )
        assert energy == pytest.approx(result.energy_history[0])

    def test_exceptions(self):
        for name, value in (
            ("discovery_rounds", -1),
            ("discovery_min_events", 0),
            ("discovery_residual_cost", 300.0),
            ("label_cost_events", 0.0),
            ("discovery_min_gain", -1.0),
            ("discovery_radius", -1),
            ("discovery_max_proposals", 0),
        ):
            with pytest.raises(ConfigError, match=name):
                GraphCutContrastSegmenter("translation", (10, 10), **{name: value})


@pytest.mark.slow
def test_quality_on_synthetic_scenes():
    """Level two alone, from perturbed true models plus two spurious ones, on 10 default affine scenes.

    Without discovery (the paper's level two), the issue's bar: accuracy >= 0.9 and every object's IoU
    >= 0.8 on 8 of 10 scenes, spurious models removed. Met on seeds 0-9 with per-polarity IWEs and the IWE
    margin (5 of 10 without); seeds 5 and 8 fail on straight object outlines that another layer's motion
    explains as well (the aperture problem) and on a small object. On seeds 10-19 it is met on 2 of 10
    (1 without), mean accuracy 0.92.

    With discovery, from this complete pool: 7 of 10 (mean accuracy 0.924 against 0.955): on seed 2 a
    proposal fitted to part of the background, whose model starts 1 px off, takes half of it.
    """
    results = {0: ([], [], []), 1: ([], [], [])}
    for seed in range(10):
        n_objects = 1 + seed % 3
        scene = make_scene((180, 240), 0.03, n_objects=n_objects, rng=seed)
        model = scene.motions[0].model
        truth = np.stack([motion.params for motion in scene.motions])
        rng = np.random.default_rng(100 + seed)
        init = truth + rng.normal(0, 1.0, truth.shape) / model.displacement_scale(0.03)
        spurious = rng.normal(0, 1, (2, truth.shape[1])) * np.array([600.0, 600.0, 3.0, 3.0])
        pool = torch.as_tensor(np.concatenate([init, spurious]), dtype=torch.float32)
        for rounds, (accuracies, worst_ious, extra) in results.items():
            segmenter = GraphCutContrastSegmenter(model, (180, 240), discovery_rounds=rounds)
            result = segmenter(to_torch(scene.events), pool)
            predicted = result.labels.numpy()
            accuracies.append(labelling_accuracy(predicted, scene.labels))
            worst_ious.append(min(per_object_iou(predicted, scene.labels).values()))
            extra.append(result.params.shape[0] - (n_objects + 1))
    for rounds, floor, (accuracies, worst_ious, extra) in ((0, 8, results[0]), (1, 7, results[1])):
        passed = [
            accuracy >= 0.9 and iou >= 0.8 for accuracy, iou in zip(accuracies, worst_ious, strict=True)
        ]
        assert sum(passed) >= floor, (rounds, accuracies, worst_ious)
        assert sum(max(count, 0) for count in extra) <= rounds, (rounds, extra)  # spurious models removed
    assert min(results[0][0]) >= 0.85, results[0][0]
    assert np.mean(results[1][0]) >= 0.9, results[1][0]
