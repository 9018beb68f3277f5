"""``evseg demo``: a synthetic scene segmented and drawn."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("evseg")


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add ``demo`` to ``commands`` (a subparsers action), with the shared options of ``common``."""
    demo = commands.add_parser(
        "demo",
        parents=[common],
        help="segment a synthetic scene and draw it",
        description="Generate a synthetic scene, segment it, and write demo.png (the paper's Fig. 1 panels) "
        "and metrics.json with the metrics against ground truth.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    demo.add_argument("--seed", type=int, default=1, help="scene seed")
    demo.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.evaluation.metrics import labelling_accuracy, match_clusters, per_object_iou
    from evseg_torch.pipeline import CascadedSegmenter
    from evseg_torch.synthetic import make_scene
    from evseg_torch.viz.panels import render_fig1, write_png

    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(sensor_size=(180, 240), duration=0.03, n_objects=2, rng=args.seed)
    segmenter = CascadedSegmenter(sensor_size=scene.sensor_size)
    result = segmenter(scene.events)
    ious = per_object_iou(result.labels, scene.labels)
    metrics = {
        "events": len(scene.events),
        "clusters": result.n_clusters,
        "true_clusters": len(scene.motions),
        "accuracy": labelling_accuracy(result.labels, scene.labels),
        "mean_imo_iou": float(np.mean(list(ious.values()))),
        "time_ms": result.timings_ms["total"],
    }
    # Draw each true layer in the colour of the cluster matched to it, so the two panels compare at a glance.
    layer_to_id = {
        layer: int(result.object_ids[cluster])
        for cluster, layer in match_clusters(result.labels, scene.labels).items()
    }
    first_spare = int(result.object_ids.max(initial=-1)) + 1
    spare = iter(range(first_spare, first_spare + len(scene.motions)))
    colour_of = {layer: layer_to_id.get(layer, next(spare)) for layer in range(len(scene.motions))}
    shown = np.array([colour_of.get(int(v), -1) for v in range(-1, len(scene.motions))])[scene.labels + 1]
    shown_metrics = {
        "clusters": f"{result.n_clusters} (true {len(scene.motions)})",
        "accuracy": metrics["accuracy"],
        "mean IMO IoU": metrics["mean_imo_iou"],
        "time": f"{metrics['time_ms']:.0f} ms",
    }
    image = render_fig1(
        result,
        title=f"evseg demo: synthetic scene, seed {args.seed}",
        metrics=shown_metrics,
        ground_truth=shown,
        ids=result.object_ids,
    )
    path = write_png(image, args.out / "demo.png")
    (args.out / "metrics.json").write_text(json.dumps({**metrics, "timings_ms": result.timings_ms}, indent=2))
    log.info("wrote %s", path)
    for key, value in metrics.items():
        log.info("%-13s %s", key, f"{value:.3f}" if isinstance(value, float) else value)
    return 0
