import itertools

import numpy as np
import pytest
import torch

from evseg_torch.backend import using_backend
from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.events import EVENT_DTYPE, EventBatch
from evseg_torch.level_two.energy.graph import event_graph, pixel_adjacency, site_graph


def _random_events(count, size=(40, 50), seed=0):
    rng = np.random.default_rng(seed)
    xy = np.column_stack([rng.integers(0, size[1], count), rng.integers(0, size[0], count)])
    return xy, np.sort(rng.random(count))


def _brute_force(xy, t, temporal_edges=False):
    """Per-event loops over the definition, for small inputs."""
    # Same pixel order as event_graph (row-major), hence the same triangulation of co-circular pixels.
    pixels = sorted({(int(x), int(y)) for x, y in xy}, key=lambda p: (p[1], p[0]))
    index = {p: i for i, p in enumerate(pixels)}
    pairs, mult = pixel_adjacency(np.array(pixels))
    neighbours = {}
    for (a, b), m in zip(pairs.tolist(), mult.tolist(), strict=True):
        neighbours.setdefault(a, []).append((b, m))
        neighbours.setdefault(b, []).append((a, m))
    order = np.lexsort((np.arange(len(t)), t))  # time, ties by index
    rank = np.empty(len(t), dtype=int)
    rank[order] = np.arange(len(t))
    found = {}
    for k in range(len(t)):
        p = index[(int(xy[k, 0]), int(xy[k, 1]))]
        for q, m in neighbours.get(p, []):
            at_q = [j for j in range(len(t)) if index[(int(xy[j, 0]), int(xy[j, 1]))] == q]
            before = [j for j in at_q if rank[j] < rank[k]]
            after = [j for j in at_q if rank[j] > rank[k]]
            for j in ([max(before, key=lambda j: rank[j])] if before else []) + (
                [min(after, key=lambda j: rank[j])] if after else []
            ):
                found[(min(j, k), max(j, k))] = m
        if temporal_edges:
            same = sorted(
                (j for j in range(len(t)) if index[(int(xy[j, 0]), int(xy[j, 1]))] == p),
                key=lambda j: rank[j],
            )
            for a, b in itertools.pairwise(same):
                found[(min(a, b), max(a, b))] = 1
    return found


class TestPixelAdjacency:
    def test_square(self):
        pairs, mult = pixel_adjacency(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]))
        # 4 sides on the hull once, one diagonal shared by both triangles.
        assert len(pairs) == 5
        assert sorted(mult.tolist()) == [1, 1, 1, 1, 2]
        assert np.all(pairs[:, 0] < pairs[:, 1])

    def test_collinear_and_tiny(self):
        pairs, mult = pixel_adjacency(np.array([[4, 2], [0, 2], [2, 2]]))
        assert sorted(map(tuple, pairs.tolist())) == [(0, 2), (1, 2)]
        assert mult.tolist() == [1, 1]
        assert pixel_adjacency(np.array([[3, 3]]))[0].shape == (0, 2)
        assert pixel_adjacency(np.array([[3, 3], [5, 1]]))[0].tolist() == [[0, 1]]

    def test_euler(self):
        # A planar triangulation of P points with h on the hull has 3P - 3 - h edges, and the
        # multiplicities sum to 3 * (number of triangles) = 3 (2P - 2 - h).
        rng = np.random.default_rng(1)
        keys = rng.choice(60 * 60, size=300, replace=False)
        pairs, mult = pixel_adjacency(np.column_stack([keys % 60, keys // 60]))
        hull = int(np.sum(mult == 1))
        assert len(pairs) == 3 * 300 - 3 - hull
        assert int(mult.sum()) == 3 * (2 * 300 - 2 - hull)


class TestEventGraph:
    def test_known_tiny_case(self):
        xy = np.array([[0, 0], [1, 0], [0, 1], [0, 0]])
        edges, weights = event_graph(xy, np.array([0.0, 1.0, 2.0, 3.0]))
        # Event 3 repeats pixel (0, 0): it sees the latest earlier events at (1, 0) and (0, 1) only;
        # same-pixel events 0 and 3 are not joined by default.
        assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
        assert weights.tolist() == [1.0] * 5
        edges, weights = event_graph(xy, np.array([0.0, 1.0, 2.0, 3.0]), temporal_edges=True)
        assert [0, 3] in edges.tolist()

    def test_interior_edges_weigh_two(self):
        xy = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])
        edges, weights = event_graph(xy, np.arange(4.0))
        diagonal = {(0, 3), (1, 2)} & {tuple(e) for e in edges.tolist()}
        assert len(diagonal) == 1
        assert weights[edges.tolist().index(list(diagonal.pop()))] == 2.0
        assert sorted(weights.tolist()) == [1.0, 1.0, 1.0, 1.0, 2.0]

    @pytest.mark.parametrize("temporal_edges", [False, True])
    def test_matches_definition(self, temporal_edges):
        xy, t = _random_events(120, size=(6, 7), seed=3)
        t = np.round(t, 1)  # many ties in time
        edges, weights = event_graph(xy, t, temporal_edges=temporal_edges)
        expected = _brute_force(xy, t, temporal_edges)
        assert {tuple(e): w for e, w in zip(edges.tolist(), weights.tolist(), strict=True)} == expected

    def test_properties(self):
        xy, t = _random_events(3000)
        edges, weights = event_graph(xy, t, (40, 50))
        assert edges.dtype == np.int64 and weights.dtype == np.float64
        assert np.all(edges[:, 0] < edges[:, 1])  # undirected, listed once, no self-loops
        keys = edges[:, 0] * 3000 + edges[:, 1]
        assert len(np.unique(keys)) == len(keys)
        assert np.all(weights > 0)
        assert set(np.unique(weights).tolist()) <= {1.0, 2.0}
        # Connected: every event has a neighbour.
        assert len(np.unique(edges)) == 3000

    def test_input_forms_agree(self):
        xy, t = _random_events(500, seed=5)
        reference = event_graph(xy, t)
        structured = np.zeros(500, dtype=EVENT_DTYPE)
        structured["x"], structured["y"], structured["t"] = xy[:, 0], xy[:, 1], np.round(t * 1e6)
        batch = EventBatch(torch.as_tensor(xy, dtype=torch.float32), torch.as_tensor(t), torch.ones(500))
        for other in (
            event_graph(structured),
            event_graph(batch),
            event_graph(torch.as_tensor(xy), torch.as_tensor(t)),
        ):
            np.testing.assert_array_equal(other[0], reference[0])
            np.testing.assert_array_equal(other[1], reference[1])

    def test_does_not_mutate(self):
        xy, t = _random_events(200, seed=2)
        copies = xy.copy(), t.copy()
        event_graph(xy, t)
        np.testing.assert_array_equal(xy, copies[0])
        np.testing.assert_array_equal(t, copies[1])

    def test_small_inputs(self):
        assert event_graph(np.array([[1, 1]]), np.array([0.0]))[0].shape == (0, 2)
        edges, _ = event_graph(np.array([[1, 1], [1, 1]]), np.array([0.0, 1.0]))
        assert edges.shape == (0, 2)
        edges, _ = event_graph(np.array([[1, 1], [1, 1]]), np.array([0.0, 1.0]), temporal_edges=True)
        assert edges.tolist() == [[0, 1]]

    def test_exceptions(self):
        with pytest.raises(ShapeError, match="times t"):
            event_graph(np.zeros((3, 2), dtype=int))
        with pytest.raises(ShapeError, match=r"\(N, 2\)"):
            event_graph(np.zeros((3, 3), dtype=int), np.zeros(3))
        with pytest.raises(ShapeError, match="integer pixels"):
            event_graph(np.full((3, 2), 0.5), np.zeros(3))
        with pytest.raises(ShapeError, match="outside the sensor"):
            event_graph(np.array([[10, 0], [0, 0]]), np.zeros(2), (5, 5))
        with pytest.raises(ShapeError, match="to match"):
            event_graph(np.zeros((3, 2), dtype=int), np.zeros(4))


def _merged(sites, edges, weights):
    """Event edges summed per site pair, within-site edges dropped, sorted by pair."""
    merged = {}
    for (a, b), w in zip(sites[edges].tolist(), weights.tolist(), strict=True):
        if a != b:
            key = (min(a, b), max(a, b))
            merged[key] = merged.get(key, 0.0) + w
    keys = sorted(merged)
    return np.array(keys, dtype=np.int64).reshape(-1, 2), np.array([merged[k] for k in keys])


class TestSiteGraph:
    @pytest.mark.parametrize(("time_slices", "temporal_edges"), itertools.product([1, 2, 5], [False, True]))
    def test_merges_the_event_graph(self, time_slices, temporal_edges):
        xy, t = _random_events(3000, size=(20, 25), seed=time_slices)
        sites, edges, weights = site_graph(xy, t, time_slices=time_slices, temporal_edges=temporal_edges)
        # A site is one pixel within one time slice.
        slot = np.minimum(((t - t.min()) / (t.max() - t.min()) * time_slices).astype(int), time_slices - 1)
        key = (xy[:, 1] * 25 + xy[:, 0]) * time_slices + slot
        assert sites.max() + 1 == len(np.unique(key))
        assert all(len(np.unique(key[sites == s])) == 1 for s in range(0, sites.max() + 1, 7))
        expected = _merged(sites, *event_graph(xy, t, temporal_edges=temporal_edges))
        order = np.lexsort((edges[:, 1], edges[:, 0]))
        np.testing.assert_array_equal(edges[order], expected[0])
        np.testing.assert_allclose(weights[order], expected[1])
        assert (edges[:, 0] < edges[:, 1]).all() and (weights > 0).all()

    @pytest.mark.parametrize("seed", range(4))
    def test_compiled_counts_equal_the_lookups(self, seed):
        pytest.importorskip("numba")
        rng = np.random.default_rng(seed)
        count = [5, 300, 3000, 20000][seed]
        xy = np.column_stack([rng.integers(0, 30, count), rng.integers(0, 20, count)])
        t = rng.integers(0, max(count // 4, 2), count)  # ties in time, broken by event order
        compiled = site_graph(xy, t)
        with using_backend("torch"):
            for found, expected in zip(compiled, site_graph(xy, t), strict=True):
                assert found.dtype == expected.dtype
                np.testing.assert_array_equal(found, expected)

    def test_small_inputs_and_exceptions(self):
        sites, edges, weights = site_graph(np.array([[3, 4]]), np.array([0.0]))
        assert sites.tolist() == [0] and edges.shape == (0, 2) and weights.shape == (0,)
        sites, _, _ = site_graph(np.array([[3, 4], [3, 4]]), np.array([0.0, 0.0]), time_slices=3)
        assert sites.tolist() == [0, 0]  # no time span: one slice
        sites, edges, weights = site_graph(np.array([[3, 4]] * 4), np.arange(4.0), time_slices=2)
        assert sites.tolist() == [0, 0, 1, 1] and edges.shape == (0, 2) and weights.dtype == np.float64
        with pytest.raises(ConfigError, match="time_slices"):
            site_graph(np.array([[3, 4]]), np.array([0.0]), time_slices=0)
        with pytest.raises(ShapeError, match="integer pixels"):
            site_graph(np.array([[3.5, 4.0]]), np.array([0.0]))
