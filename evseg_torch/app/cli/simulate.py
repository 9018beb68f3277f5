"""``evseg simulate``: synthetic scenes with ground truth written as ``.npz`` files."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from evseg_torch.app.cli.options import seed_range, sensor_size

log = logging.getLogger("evseg")


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add ``simulate`` to ``commands`` (a subparsers action), with the shared options of ``common``."""
    simulate = commands.add_parser(
        "simulate",
        parents=[common],
        help="write synthetic scenes with ground truth",
        description="Write synthetic event scenes as .npz files (events t_us/x/y/p, per-event labels as "
        "`labels` and `label`, `ambiguous` flags, motions, sensor size): the layout of "
        "../shared/data/synthetic_probe, which `evseg evaluate labelled` scores.",
    )
    simulate.add_argument("--out", required=True, type=Path, help="output folder")
    simulate.add_argument("--seeds", type=seed_range, default=[0], help="seeds, e.g. 0-9 or 3")
    simulate.add_argument("--sensor-size", type=sensor_size, default=(180, 240), help="HxW (default 180x240)")
    simulate.add_argument("--duration-ms", type=float, default=30.0, help="scene length (default 30 ms)")
    simulate.add_argument("--objects", type=int, default=2, help="number of moving objects (default 2)")
    simulate.add_argument("--motion-model", default="affine4", help="translation, affine4 or rotation3d")
    simulate.add_argument(
        "--family",
        help="a named scene family instead (hard: known failure modes); ignores --objects and --motion-model",
    )
    simulate.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.synthetic import make_scene
    from evseg_torch.synthetic.families import make_family_scene

    args.out.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        if args.family:
            scene = make_family_scene(args.family, seed, args.sensor_size, args.duration_ms / 1000)
        else:
            scene = make_scene(
                sensor_size=args.sensor_size,
                duration=args.duration_ms / 1000,
                n_objects=args.objects,
                motion_model=args.motion_model,
                rng=seed,
            )
        path = args.out / f"scene_{seed:04d}.npz"
        np.savez_compressed(
            path,
            t_us=scene.events["t"],
            x=scene.events["x"],
            y=scene.events["y"],
            p=scene.events["p"],
            labels=scene.labels,
            label=scene.labels,
            ambiguous=scene.ambiguous,
            height=scene.sensor_size[0],
            width=scene.sensor_size[1],
            sensor_size=np.array(scene.sensor_size, dtype=np.int32),
            motion_models=np.array([m.model.name for m in scene.motions]),
            motion_params=np.array([np.pad(m.params, (0, 4 - len(m.params))) for m in scene.motions]),
        )
        log.info("wrote %s (%d events)", path, len(scene.events))
    return 0
