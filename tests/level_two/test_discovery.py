import numpy as np
import pytest
import torch

from evseg_torch.events import EventBatch
from evseg_torch.level_two.discovery import (
    bisect,
    candidate_regions,
    centroid_velocity,
    recentred,
    translation_params,
)
from evseg_torch.level_two.solver.crops import gather_members
from evseg_torch.motion import Affine4, Rotation3D, Translation

SIZE = (40, 60)  # (H, W)


def _block(x0, x1, y0, y1):
    """Every integer pixel of ``[x0, x1) x [y0, y1)``, :math:`(n, 2)` with ``x`` the column."""
    xs, ys = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
    return np.column_stack([xs.ravel(), ys.ravel()]).astype(np.int64)


def _layout(*blocks):
    """Events at the pixels of labelled blocks ``(label, (x0, x1, y0, y1))``: ``xy``, ``labels`` and the
    indices of each block's events, in the order given."""
    xy, labels, index, start = [], [], [], 0
    for label, box in blocks:
        pixels = _block(*box)
        xy.append(pixels)
        labels.append(np.full(len(pixels), label))
        index.append(np.arange(start, start + len(pixels)))
        start += len(pixels)
    return np.concatenate(xy), np.concatenate(labels), index


def _regions(
    xy, labels, own_cost=None, min_events=20, residual_cost=None, radius=2, around=None, carried=False
):
    own_cost = np.zeros(len(labels)) if own_cost is None else own_cost
    regions = candidate_regions(
        xy,
        labels,
        own_cost,
        SIZE,
        min_events=min_events,
        residual_cost=residual_cost,
        radius=radius,
        around=around,
        carried=carried,
    )
    sizes = [len(members) for _, members in regions]
    assert sizes == sorted(sizes, reverse=True)  # largest regions first
    for _, members in regions:
        assert members.dtype == np.int64 and len(np.unique(members)) == len(members)
    return regions


def _as_sets(regions):
    return [(cluster, frozenset(members.tolist())) for cluster, members in regions]


def _union(*parts):
    return frozenset(np.concatenate(parts).tolist())


class TestBisect:
    def test_two_blobs_come_out_as_the_halves(self):
        rng = np.random.default_rng(0)
        # Two blobs of different sizes along a diagonal, among unrelated events that are not members.
        first = np.rint(rng.normal([12.0, 10.0], 2.0, (150, 2)))
        second = np.rint(rng.normal([45.0, 30.0], 2.0, (60, 2)))
        other = rng.uniform(0, 60, (100, 2)).round()
        xy = np.concatenate([other, first, second]).astype(np.int64)
        order = rng.permutation(len(first) + len(second))
        members = (100 + np.arange(len(first) + len(second)))[order]
        halves = bisect(xy, members)
        assert len(halves) == 2
        got = sorted((frozenset(half.tolist()) for half in halves), key=len)
        assert got == [frozenset(range(250, 310)), frozenset(range(100, 250))]

    def test_halves_partition_the_members(self):
        rng = np.random.default_rng(1)
        xy = rng.integers(0, 60, (400, 2))
        members = rng.choice(400, 250, replace=False)
        halves = bisect(xy, members)
        joined = np.concatenate(halves)
        assert len(joined) == len(members) and set(joined.tolist()) == set(members.tolist())
        assert all(len(half) > 0 for half in halves)
        # The cut is across the principal axis: the halves do not overlap along it.
        points = xy[members].astype(np.float64)
        axis = np.linalg.svd(points - points.mean(0))[2][0]
        low, high = sorted((xy[half] @ axis for half in halves), key=np.mean)
        assert low.max() <= high.min()


class TestCandidateRegions:
    def test_cluster_of_two_groups_proposes_each(self):
        xy, labels, (_, first, second, speck) = _layout(
            (0, (0, 20, 0, 40)),
            (1, (32, 38, 2, 10)),
            (1, (32, 38, 26, 34)),
            (1, (55, 58, 36, 39)),  # 9 events: fewer than min_events
        )
        regions = _as_sets(_regions(xy, labels))
        from_one = [members for cluster, members in regions if cluster == 1]
        assert sorted(from_one, key=min) == [frozenset(first.tolist()), frozenset(second.tolist())]
        # Neither group is bisected, and the small group is not proposed anywhere.
        assert all(not members & set(speck.tolist()) for _, members in regions)

    def test_single_group_bisected_unless_largest(self):
        xy, labels, (background, bar) = _layout((0, (0, 20, 0, 40)), (1, (30, 54, 20, 26)))
        regions = _regions(xy, labels)
        halves = [members for cluster, members in regions if cluster == 1]
        assert len(halves) == 2 and all(len(half) >= 20 for half in halves)
        assert sorted(np.concatenate(halves).tolist()) == bar.tolist()
        # The bar lies along x: the halves are its left and right parts.
        left, right = sorted(halves, key=lambda half: xy[half, 0].mean())
        assert xy[left, 0].max() < xy[right, 0].min()
        # The largest cluster is not bisected: a region from it holds all of it.
        assert all(set(members.tolist()) == set(background.tolist()) for c, members in regions if c == 0)

    def test_halves_below_min_events_are_dropped(self):
        xy, labels, _ = _layout((0, (0, 20, 0, 40)), (1, (30, 40, 20, 24)))  # 40 events, halves of 20
        assert [c for c, _ in _regions(xy, labels, min_events=20)].count(1) == 2
        assert [c for c, _ in _regions(xy, labels, min_events=21)].count(1) == 0
        assert _regions(xy, labels, min_events=900) == []

    def test_touching_clusters_propose_their_union(self):
        xy, labels, (_, first, second, far) = _layout(
            (0, (0, 20, 0, 40)),
            (1, (30, 40, 5, 15)),  # 100 events
            (2, (40, 46, 5, 15)),  # 60 events, touching cluster 1
            (3, (30, 40, 30, 34)),  # 40 events, far from both
        )
        regions = _as_sets(_regions(xy, labels))
        merged = [(cluster, members) for cluster, members in regions if len(members) > 100]
        # One union (the background's region aside), from the larger cluster of the pair.
        assert (1, _union(first, second)) in regions
        assert [m for c, m in merged if c != 0] == [_union(first, second)]
        assert all(not (members & set(far.tolist()) and len(members) > len(far)) for _, members in regions)
        # The largest cluster is never merged, even where it touches another.
        xy, labels, _ = _layout((0, (0, 20, 0, 40)), (1, (20, 30, 0, 10)))
        assert all(len(members) < len(labels) for _, members in _regions(xy, labels))

    def test_a_later_round_proposes_only_around_new_clusters(self):
        xy, labels, (_, first, second, far) = _layout(
            (0, (0, 20, 0, 40)),
            (1, (30, 40, 5, 15)),
            (2, (40, 46, 5, 15)),  # touching cluster 1
            (3, (30, 40, 30, 34)),  # far from both
        )
        regions = _regions(xy, labels)
        new = np.array([False, False, True, False])
        kept = _regions(xy, labels, around=new)
        # Cluster 2's own regions and its union with cluster 1; nothing of clusters 0, 1 or 3 alone.
        assert _as_sets(kept) == [region for region in _as_sets(regions) if region[1] & set(second.tolist())]
        assert (1, _union(first, second)) in _as_sets(kept)
        assert all(not members & set(far.tolist()) for _, members in _as_sets(kept))
        assert _regions(xy, labels, around=np.zeros(4, dtype=bool)) == []

    def test_carried_clusters_propose_only_their_separate_groups(self):
        xy, labels, (_, first, second, far, other) = _layout(
            (0, (0, 20, 0, 40)),
            (1, (30, 40, 5, 15)),
            (2, (40, 46, 5, 15)),  # touching cluster 1
            (3, (30, 40, 30, 34)),  # far from both, one group
            (3, (50, 58, 30, 34)),  # a second group of cluster 3
        )
        everything = _as_sets(_regions(xy, labels))
        assert (1, _union(first, second)) in everything  # a union and halves, in a window of its own
        assert sum(cluster == 1 for cluster, _ in everything) > 1
        carried = _as_sets(_regions(xy, labels, carried=True))
        # No halves, no unions: only cluster 3's two groups.
        assert sorted(members for cluster, members in carried if cluster == 3) == sorted(
            [frozenset(far.tolist()), frozenset(other.tolist())], key=min
        )
        assert {cluster for cluster, _ in carried} == {3}

    def test_residual_regions(self):
        xy, labels, (_, first, second, _) = _layout(
            (0, (0, 20, 0, 40)),
            (1, (30, 40, 5, 15)),
            (2, (40, 46, 5, 15)),
            (0, (50, 51, 30, 31)),  # one far background event
        )
        own_cost = np.zeros(len(labels))
        # A streak its models explain badly: all of cluster 2 and the adjacent column of cluster 1.
        column = first[xy[first, 0] == 39]
        streak = np.concatenate([second, column])
        own_cost[streak] = 200.0
        own_cost[-1] = 255.0  # alone: fewer than min_events
        plain = _as_sets(_regions(xy, labels, own_cost))
        assert plain == _as_sets(_regions(xy, labels, own_cost, residual_cost=None))
        with_residual = _as_sets(_regions(xy, labels, own_cost, residual_cost=150.0))
        extra = [region for region in with_residual if region not in plain]
        assert extra == [(2, frozenset(streak.tolist()))]  # majority cluster 2 (60 of its 70 events)
        assert len(with_residual) == len(plain) + 1
        # Above every event's cost: nothing is residual.
        assert _as_sets(_regions(xy, labels, own_cost, residual_cost=250.0)) == plain
        # A later round keeps the streak where it holds events of a new cluster (1 or 2), not elsewhere.
        for new, kept in (([False, True, False], True), ([True, False, False], False)):
            around = _as_sets(_regions(xy, labels, own_cost, residual_cost=150.0, around=np.array(new)))
            assert ((2, frozenset(streak.tolist())) in around) == kept

    def test_radius_joins_sparse_events(self):
        # A sparse object (events 3 pixels apart) is one group at radius 2, many specks at radius 0.
        sparse = _block(0, 10, 0, 10) * 3 + [25, 5]
        xy = np.concatenate([_block(0, 20, 0, 40), sparse]).astype(np.int64)
        labels = np.repeat([0, 1], [800, 100])
        joined = _regions(xy, labels, radius=2)
        assert sum(len(m) for c, m in joined if c == 1) == 100  # its two halves
        assert [c for c, _ in _regions(xy, labels, radius=0)].count(1) == 0

    def test_empty(self):
        empty = np.zeros((0, 2), dtype=np.int64)
        assert _regions(empty, np.zeros(0, dtype=np.int64)) == []


def _blob_events(rng, centre, velocity, n_points=40, n_times=50, duration=0.03, radius=4.0):
    """A blob of texture points translating at ``velocity`` px/s, every point firing at the same evenly
    spaced times, positions rounded to pixels: its centroid moves at ``velocity`` up to rounding."""
    points = np.asarray(centre) + rng.uniform(-radius, radius, (n_points, 2))
    t = np.linspace(0.0, duration, n_times)
    xy = np.rint(points[None] + t[:, None, None] * np.asarray(velocity)).reshape(-1, 2)
    return xy, np.repeat(t, n_points)


class TestCentroidVelocity:
    def test_translating_blobs(self, device, dtype):
        rng = np.random.default_rng(0)
        velocities = np.array([[300.0, -150.0], [-200.0, 250.0]])
        parts = [
            _blob_events(rng, centre, v) for centre, v in zip([[15, 30], [45, 10]], velocities, strict=True)
        ]
        # A third set all at one time, and the events shuffled so that no set is contiguous.
        still = (rng.uniform(20, 40, (50, 2)), np.full(50, 0.01))
        xy = np.concatenate([p[0] for p in parts] + [still[0]])
        t = np.concatenate([p[1] for p in parts] + [still[1]])
        owner = np.repeat([0, 1, 2], [len(parts[0][1]), len(parts[1][1]), 50])
        order = rng.permutation(len(t))
        xy, t, owner = xy[order], t[order], owner[order]
        events = EventBatch(
            torch.as_tensor(xy, dtype=dtype, device=device),
            torch.as_tensor(t, dtype=dtype, device=device),
            torch.ones(len(t), dtype=dtype, device=device),
        )
        weights = torch.as_tensor(owner[None] == np.arange(3)[:, None], dtype=dtype, device=device)
        velocity = centroid_velocity(events, weights)
        assert velocity.shape == (3, 2) and velocity.dtype == dtype
        velocity = velocity.cpu().double().numpy()
        for k in range(2):
            assert np.linalg.norm(velocity[k] - velocities[k]) < 0.01 * np.linalg.norm(velocities[k])
        assert np.all(velocity[2] == 0)
        # Scaling a set's weights changes nothing.
        scaled = centroid_velocity(events, 3.0 * weights).cpu().double().numpy()
        np.testing.assert_allclose(scaled, velocity, rtol=1e-4, atol=1e-3)

    def test_empty_set_is_zero(self):
        events = EventBatch(torch.rand(10, 2), torch.rand(10), torch.ones(10))
        assert torch.all(centroid_velocity(events, torch.zeros(1, 10)) == 0)


def _pixels(rng, n, dtype=torch.float64, device="cpu"):
    return torch.as_tensor(
        rng.uniform([0, 0], [SIZE[1] - 1, SIZE[0] - 1], (n, 2)), dtype=dtype, device=device
    )


class TestTranslationParams:
    @pytest.mark.parametrize(
        ("model", "padding"),
        [(Translation(SIZE), []), (Affine4(SIZE), [0.0, 0.0])],
        ids=["translation", "affine4"],
    )
    def test_exact_translation(self, model, padding, device, dtype):
        rng = np.random.default_rng(0)
        xy = _pixels(rng, 300, dtype, device)
        # Two sets: a blob in one corner (soft weights) and every event.
        weights = torch.stack([(xy[:, 0] < 15).to(dtype) * 0.5, torch.ones(300, dtype=dtype, device=device)])
        velocity = torch.tensor([[300.0, -150.0], [-20.0, 80.0]], dtype=dtype, device=device)
        params = translation_params(model, xy, weights, velocity)
        expected = torch.cat([velocity, velocity.new_tensor(padding).expand(2, -1)], dim=1)
        # Exact up to the solver's relative ridge of 1e-9 (a few 1e-6 of the velocity, in 1/s for d and r).
        torch.testing.assert_close(params, expected, atol=1e-4, rtol=2e-5)
        for k in range(2):
            field = model.velocity(xy, params[k])
            torch.testing.assert_close(field, velocity[k].expand_as(field), atol=6e-3, rtol=0)

    def test_rotation_best_approximation(self):
        # Rotation3D cannot translate uniformly: the least-squares fit beats any nearby parameters.
        model, rng = Rotation3D(SIZE), np.random.default_rng(1)
        xy = _pixels(rng, 200)
        weights = torch.ones(1, 200, dtype=torch.float64)
        velocity = torch.tensor([[120.0, -60.0]], dtype=torch.float64)
        params = translation_params(model, xy, weights, velocity)[0]

        def residual(p):
            return float((model.velocity(xy, p) - velocity).square().sum())

        assert residual(params) < residual(torch.zeros(3, dtype=torch.float64))
        for step in torch.eye(3, dtype=torch.float64) * 1e-3 * params.abs().max():
            assert residual(params) <= min(residual(params + step), residual(params - step))


class TestRecentred:
    def test_affine4_keeps_rotation_and_scale(self, device, dtype):
        model, rng = Affine4(SIZE), np.random.default_rng(2)
        xy = _pixels(rng, 400, dtype, device)
        weights = torch.stack([(xy[:, 0] > 40).to(dtype), (xy[:, 1] < 10).to(dtype) * 2.0])
        params = torch.tensor(
            [[100.0, 50.0, 2.0, -1.5], [-80.0, 20.0, -1.0, 3.0]], dtype=dtype, device=device
        )
        velocity = torch.tensor([[300.0, -150.0], [0.0, 40.0]], dtype=dtype, device=device)
        moved = recentred(model, xy, weights, params, velocity)
        # Exact up to the solver's relative ridge of 1e-9.
        torch.testing.assert_close(moved[:, 2:], params[:, 2:], atol=1e-4, rtol=0)
        for k in range(2):
            field = model.velocity(xy, moved[k])
            mean = (weights[k, :, None] * field).sum(0) / weights[k].sum()
            torch.testing.assert_close(mean, velocity[k], atol=1e-3, rtol=0)
        # The set's mean velocity moved, not the field's shape: differences between points are kept.
        before, after = model.velocity(xy, params[0]), model.velocity(xy, moved[0])
        torch.testing.assert_close(after - after[:1], before - before[:1], atol=1e-2, rtol=0)

    def test_translation_becomes_the_velocity(self):
        model, rng = Translation(SIZE), np.random.default_rng(3)
        xy = _pixels(rng, 50)
        velocity = torch.tensor([[-70.0, 10.0]], dtype=torch.float64)
        moved = recentred(
            model, xy, torch.ones(1, 50, dtype=torch.float64), torch.tensor([[5.0, 6.0]]).double(), velocity
        )
        torch.testing.assert_close(moved, velocity)


def test_gathered_events_give_the_shared_results():
    """Each set's own (gathered, padded) events give what the shared events with weights give."""
    rng = np.random.default_rng(3)
    xy = torch.as_tensor(rng.uniform(0, 100, (300, 2)))
    events = EventBatch(xy, torch.as_tensor(rng.uniform(0, 0.03, 300)), torch.ones(300, dtype=xy.dtype))
    weights = torch.as_tensor((rng.uniform(size=(3, 300)) < 0.3).astype(np.float64))
    own, own_weights = gather_members(events, weights)
    model = Affine4((100, 100))
    velocity = centroid_velocity(events, weights)
    torch.testing.assert_close(centroid_velocity(own, own_weights), velocity)
    params = torch.as_tensor(rng.normal(0, 1, (3, 4)))
    torch.testing.assert_close(
        translation_params(model, own.xy, own_weights, velocity),
        translation_params(model, xy, weights, velocity),
    )
    torch.testing.assert_close(
        recentred(model, own.xy, own_weights, params, velocity),
        recentred(model, xy, weights, params, velocity),
    )
