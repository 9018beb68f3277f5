"""Whether a change moved any label: this checkout's labels against a tagged release's, window by window.

A change that should not move a result (a refactor, an exact speed-up) is checked here: the pipeline
segments the probe's 24 labelled scenes, the ``hard`` family's scenes, the synthetic benchmark's scenes
and the boxed windows of the EED sequences in ``../shared/data/real``, once per pipeline seed, and each
window's labels (and, for information, its models) are reduced to a SHA-256 digest. ``--baseline REV``
checks the release out into a temporary git worktree, records its digests with the same interpreter,
and lists every window whose labels differ::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/compare_labels.py --baseline v0.7

The digests are exact, so compare on one machine: another CPU may round otherwise. ``record`` writes
one checkout's digests to a JSON file, ``compare`` two such files.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
EED_SEQUENCES = ("what_is_background", "occlusions", "multiple_objects_2objs_first_half")


def digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]


def _family_scene(family: str, seed: int):
    """The family scene of ``seed``, wherever this checkout keeps the families."""
    try:
        from evseg_torch.synthetic.families import make_family_scene
    except ImportError:
        from evseg_torch.synthetic_families import make_family_scene
    return make_family_scene(family, seed, sensor_size=(180, 240), duration=0.03)


def record(pipeline_seeds: list[int], hard_seeds: list[int], own_seeds: list[int]) -> dict:
    """Each window's digests, keyed ``set/case/seed``."""
    import torch

    from evseg_torch.config import SegmenterConfig, bundled_config, load_config, replace_config
    from evseg_torch.evaluation.eed import evaluate_sequence, load_eed_sequence
    from evseg_torch.evaluation.labelled import load_labelled
    from evseg_torch.pipeline import CascadedSegmenter
    from evseg_torch.synthetic import make_scene

    torch.set_num_threads(1)
    digests = {}

    def keep(key: str, segmentation) -> None:
        digests[key] = {
            "labels": digest(np.asarray(segmentation.labels, dtype=np.int64)),
            "models": digest(np.asarray(segmentation.models, dtype=np.float64)),
        }

    probe = sorted((SHARED / "synthetic_probe").glob("*.npz"))
    eed = [SHARED / "real" / f"eed_{name}" for name in EED_SEQUENCES]
    for seed in pipeline_seeds:
        config = replace_config(SegmenterConfig(), seed=seed)
        for path in probe:
            events, _, _, size = load_labelled(path)
            keep(f"probe/{path.stem}/{seed}", CascadedSegmenter(size, config)(events))
        segmenter = CascadedSegmenter((180, 240), config)
        for scene_seed in hard_seeds:
            keep(f"hard/{scene_seed}/{seed}", segmenter(_family_scene("hard", scene_seed).events))
        for scene_seed in own_seeds:
            scene = make_scene(
                sensor_size=(180, 240), duration=0.03, n_objects=1 + scene_seed % 3, rng=scene_seed
            )
            keep(f"own/{scene_seed}/{seed}", segmenter(scene.events))
        eed_config = replace_config(load_config(bundled_config("eed")), seed=seed)
        for folder in eed:
            if not folder.is_dir():
                continue
            sequence = load_eed_sequence(folder)
            windows = []
            evaluate_sequence(
                sequence,
                eed_config,
                on_window=lambda result, segmentation, kept=windows: kept.append(segmentation),
            )
            for index, segmentation in enumerate(windows):
                keep(f"eed/{sequence.name}/{index}/{seed}", segmentation)
    return digests


def compare(baseline: dict, current: dict) -> int:
    """Print the windows whose labels differ (and those whose models alone do); 1 if any labels differ."""
    missing = sorted(set(baseline) ^ set(current))
    shared = sorted(set(baseline) & set(current))
    labels = [key for key in shared if baseline[key]["labels"] != current[key]["labels"]]
    models = [
        key for key in shared if baseline[key]["models"] != current[key]["models"] and key not in labels
    ]
    for key in labels:
        print(f"labels differ: {key}")
    for key in models:
        print(f"models differ (labels equal): {key}")
    for key in missing:
        print(f"only in one run: {key}")
    sets = sorted({key.split("/")[0] for key in shared})
    print(
        f"{len(shared)} windows ({', '.join(sets)}): {len(labels)} with other labels, "
        f"{len(models)} with other models only, {len(missing)} in one run only"
    )
    return 1 if labels or missing else 0


def _seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def _record_args(args) -> list[str]:
    return [
        "--pipeline-seeds",
        args.pipeline_seeds,
        "--hard-seeds",
        args.hard_seeds,
        "--own-seeds",
        args.own_seeds,
    ]


def _record_release(revision: str, args, out: Path) -> None:
    """Record the digests of ``revision`` from a temporary worktree, with this interpreter."""
    with tempfile.TemporaryDirectory() as folder:
        tree = Path(folder) / "tree"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), revision], check=True
        )
        try:
            env = {**os.environ, "PYTHONPATH": str(tree)}
            command = [sys.executable, __file__, "record", *_record_args(args), "--out", str(out)]
            subprocess.run(command, check=True, env=env, cwd=tree)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", nargs="?", choices=("record", "compare"), help="one step alone")
    parser.add_argument("files", nargs="*", type=Path, help="compare: the two JSON files")
    parser.add_argument("--baseline", metavar="REV", help="the release to compare with, e.g. v0.7")
    parser.add_argument("--out", type=Path, help="record: the JSON file to write")
    parser.add_argument("--pipeline-seeds", default="0-2", help="pipeline seeds (default 0-2)")
    parser.add_argument("--hard-seeds", default="0-59", help="hard-family scene seeds (default 0-59)")
    parser.add_argument("--own-seeds", default="0-19", help="synthetic benchmark seeds (default 0-19)")
    args = parser.parse_args()
    if args.command == "compare":
        baseline, current = (json.loads(path.read_text()) for path in args.files)
        return compare(baseline, current)
    seeds = [_seeds(text) for text in (args.pipeline_seeds, args.hard_seeds, args.own_seeds)]
    if args.command == "record":
        start = time.perf_counter()
        args.out.write_text(json.dumps(record(*seeds), indent=1))
        print(f"recorded {args.out} in {time.perf_counter() - start:.0f} s")
        return 0
    if not args.baseline:
        parser.error("give --baseline REV, or a command")
    with tempfile.TemporaryDirectory() as folder:
        base, current = Path(folder) / "baseline.json", Path(folder) / "current.json"
        _record_release(args.baseline, args, base)
        current.write_text(json.dumps(record(*seeds), indent=1))
        return compare(json.loads(base.read_text()), json.loads(current.read_text()))


if __name__ == "__main__":
    sys.exit(main())
