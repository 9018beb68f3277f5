"""The true-model ceiling of level two: the pipeline started from each scene's true motions.

Level one is skipped (``level_one.initial_models: replace``) and level two starts from the true model of
every layer (background and objects), then labels, refits and discovers as usual, scored as
``evseg evaluate synthetic`` scores. The gap to the pipeline's own figures is what level one's pool
costs; what remains is the energy's own limit. Our generator's scenes carry their motions in the
project's convention: the ``hard`` family and the default scenes (the probe's motions are about each
layer's own centre, so the probe is not scored here).

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_ceiling.py [--hard 0-59] [--own 0-19]
"""

import argparse

from evseg_torch.cli import _seed_range
from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.pipeline import CascadedSegmenter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hard", type=_seed_range, default=list(range(60)), help="hard-family seeds")
    parser.add_argument("--own", type=_seed_range, default=list(range(20)), help="default-scene seeds")
    args = parser.parse_args()
    segmenter = CascadedSegmenter((180, 240), replace_config(SegmenterConfig(), initial_models="replace"))
    print(f"{'set':<6} {'accuracy':>8} {'IoU':>6} {'detect':>6} {'|count|':>7}")
    for name, family, seeds in (("hard", "hard", args.hard), ("own", None, args.own)):
        s = summarize(evaluate_synthetic(segmenter, seeds, family=family, true_models=True))
        scores = f"{s['accuracy']:>8.3f} {s['iou']:>6.3f} {s['detection']:>6.3f} {s['abs_count_error']:>7.2f}"
        print(f"{name:<6} {scores}")


if __name__ == "__main__":
    main()
