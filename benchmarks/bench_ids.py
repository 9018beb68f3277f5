"""Object ids across windows: how often an object detected in two consecutive windows keeps its id.

Each scene of the ``hard`` family (:mod:`evseg_torch.synthetic.families`) is generated 0.3 s long (its
objects move through all ten 30 ms windows; a seed whose motions cannot stay in view that long is
skipped) and streamed as ``evseg segment`` does. In every window, clusters are matched to the true
layers (:func:`evseg_torch.evaluation.metrics.match_clusters`, ambiguous and noise events left out);
an object is *detected* when its matched cluster's event IoU is at least 0.5. For
every pair of consecutive windows in which an object is detected in both, its clusters' object ids are
compared; printed: the fraction of such pairs that keep the id, per kind of scene and overall, against
the cluster index (what ids were before tracking), and how often the background has id 0.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_ids.py [--seeds 0-47] [--batch-size 1]
"""

import argparse
import itertools
from collections import defaultdict

import numpy as np

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.errors import ConfigError
from evseg_torch.evaluation.metrics import match_clusters, per_object_iou
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic.families import family_kinds, make_family_scene


def detections(result, scene) -> dict[int, int]:
    """``{layer: cluster}`` of each true layer (background included) detected in a streamed window."""
    window = slice(result.offset, result.offset + len(result.labels))
    truth = np.where(scene.ambiguous[window], -1, scene.labels[window])
    matched = {layer: cluster for cluster, layer in match_clusters(result.labels, truth).items()}
    ious = per_object_iou(result.labels, truth, objects=range(len(scene.motions)))
    return {layer: matched[layer] for layer, iou in ious.items() if iou >= 0.5}


def id_pairs(results, scene) -> dict[str, list[bool]]:
    """For each consecutive pair of windows and each object detected in both: whether it kept its id
    (``tracked``) and whether it kept its cluster index (``index``); ``background``: whether a detected
    background has id 0."""
    kept = defaultdict(list)
    found = [detections(result, scene) for result in results]
    for result, seen in zip(results, found, strict=True):
        if 0 in seen:
            kept["background"].append(bool(result.object_ids[seen[0]] == 0))
    for (before, seen_before), (after, seen_after) in itertools.pairwise(zip(results, found, strict=True)):
        if after.window_index != before.window_index + 1:
            continue
        for layer in set(seen_before) & set(seen_after) - {0}:
            a, b = seen_before[layer], seen_after[layer]
            kept["tracked"].append(bool(before.object_ids[a] == after.object_ids[b]))
            kept["index"].append(a == b)
    return kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--seeds", type=seed_range, default=list(range(48)), help="scene seeds (default 0-47)"
    )
    parser.add_argument("--duration-ms", type=float, default=300.0, help="scene length (default 300 ms)")
    parser.add_argument("--batch-size", type=int, default=1, help="windows segmented together (default 1)")
    args = parser.parse_args()
    set_threads(1)
    by_kind: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    for seed in args.seeds:
        try:
            scene = make_family_scene("hard", seed, duration=args.duration_ms * 1e-3)
        except ConfigError as err:
            print(f"seed {seed:2d} skipped: {err}")
            continue
        segmenter = CascadedSegmenter(scene.sensor_size)
        results = list(segmenter.stream(scene.events, window_ms=30.0, batch_size=args.batch_size))
        kept = id_pairs(results, scene)
        kind = family_kinds("hard", seed)[0]
        for name, values in kept.items():
            by_kind[kind][name] += values
            by_kind["all"][name] += values
        largest = max(int(r.object_ids.max()) for r in results)
        print(
            f"seed {seed:2d} {'+'.join(family_kinds('hard', seed)):18s} {len(results)} windows, "
            f"objects {scene.n_objects}, kept {sum(kept['tracked'])}/{len(kept['tracked'])}, "
            f"largest id {largest}"
        )
    print(f"{'kind':>10}  pairs  id kept  index kept  background id 0")
    for kind, kept in by_kind.items():
        tracked, index, background = kept["tracked"], kept["index"], kept["background"]
        print(
            f"{kind:>10}  {len(tracked):5d}  {np.mean(tracked):7.3f}  {np.mean(index):10.3f}"
            f"  {np.mean(background):.3f} of {len(background)}"
        )


if __name__ == "__main__":
    main()
