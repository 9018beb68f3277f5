"""Benchmark α-expansion on a level-two-sized problem: 30k nodes, ~200k kNN edges, 4 labels, 2 cycles.

Nodes are random points on a 346 x 260 sensor in random order (like events sorted by time), joined
to their k nearest neighbours; the data costs are uniform noise with the node's true label (one of
four quadrants) cheaper by ``--margin``. Prints the time of ``potts_graph`` (once per graph) and medians
over ``--repeats`` runs of the whole call on that graph, per cycle, per move and per maximum flow
(PyMaxflow is single-threaded).

    .venv/bin/python benchmarks/bench_graphcut.py [--nodes 30000 --neighbours 12 --label-cost 100]
"""

import argparse
import importlib
import time
from types import SimpleNamespace
from unittest import mock

import maxflow
import numpy as np
from scipy.spatial import cKDTree

# The package re-exports the function under the module's own name, so fetch the module itself.
expansion_module = importlib.import_module("evseg_torch.graphcut.alpha_expansion")

FLOW_SECONDS: list[float] = []
MOVE_SECONDS: list[float] = []


class _TimedGraph(maxflow.GraphFloat):
    def maxflow(self, *args):
        start = time.perf_counter()
        flow = super().maxflow(*args)
        FLOW_SECONDS.append(time.perf_counter() - start)
        return flow


def _timed_expand(*args):
    start = time.perf_counter()
    expanded = _expand(*args)
    MOVE_SECONDS.append(time.perf_counter() - start)
    return expanded


_expand = expansion_module._expand


def make_problem(n_nodes, n_neighbours, n_labels, margin, seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform((0, 0), (346, 260), size=(n_nodes, 2))
    _, neighbours = cKDTree(points).query(points, k=n_neighbours + 1)
    edges = np.stack([np.repeat(np.arange(n_nodes), n_neighbours), neighbours[:, 1:].ravel()], axis=1)
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    truth = (points[:, 0] > 173).astype(int) + 2 * (points[:, 1] > 130)
    unary = rng.uniform(0, 1, size=(n_nodes, n_labels))
    unary[np.arange(n_nodes), truth % n_labels] -= margin
    return unary, edges, truth % n_labels


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=30_000)
    parser.add_argument("--neighbours", type=int, default=12, help="k of the kNN graph")
    parser.add_argument("--labels", type=int, default=4)
    parser.add_argument("--cycles", type=int, default=2)
    parser.add_argument("--smoothness", type=float, default=0.3)
    parser.add_argument("--label-cost", type=float, nargs="+", default=[0.0, 100.0])
    parser.add_argument("--margin", type=float, nargs="+", default=[0.3, 1.0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    for margin in args.margin:
        unary, edges, truth = make_problem(args.nodes, args.neighbours, args.labels, margin, args.seed)
        print(
            f"N={len(unary)} E={len(edges)} L={args.labels} cycles={args.cycles} "
            f"smoothness={args.smoothness} margin={margin}"
        )
        layout_seconds = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            graph = expansion_module.potts_graph(edges, n_nodes=len(unary))
            layout_seconds.append(time.perf_counter() - start)
        layout_ms = np.median(layout_seconds) * 1e3
        print(f"  potts_graph (validation and node numbering, once per graph): {layout_ms:.1f} ms")
        for label_cost in args.label_cost:
            totals, cycles = [], []
            FLOW_SECONDS.clear()
            MOVE_SECONDS.clear()
            patched = SimpleNamespace(Graph={float: _TimedGraph})
            with (
                mock.patch.object(expansion_module, "maxflow", patched),
                mock.patch.object(expansion_module, "_expand", _timed_expand),
            ):
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    result = expansion_module.alpha_expansion(
                        unary,
                        graph,
                        smoothness=args.smoothness,
                        label_cost=label_cost,
                        max_cycles=args.cycles,
                    )
                    totals.append(time.perf_counter() - start)
                    cycles.append(result.n_cycles)
            total = np.median(totals)
            accuracy = (result.labels == truth).mean()
            print(
                f"  label_cost={label_cost:g}: total {total * 1e3:7.1f} ms, "
                f"per cycle {total / np.median(cycles) * 1e3:7.1f} ms, "
                f"per move {np.median(MOVE_SECONDS) * 1e3:6.1f} ms "
                f"(max flow {np.median(FLOW_SECONDS) * 1e3:6.1f} ms), "
                f"{len(MOVE_SECONDS) // args.repeats} moves, accuracy {accuracy:.3f}"
            )


if __name__ == "__main__":
    main()
