"""One fit evaluation (a cluster's contrast loss and its gradient) by each of its three forms.

The refits and discovery evaluate ``warped_contrast_loss_and_grad`` (the gradient chained by hand; the
``torch`` backend) or its compiled loop (``evseg_torch/kernels/fit.py``; the ``numba`` backend) a few
dozen times per window; ``autograd`` is the same loss differentiated by autograd
(``warped_contrast_loss``, the learning pipelines' form), for comparison. Each case is one affine4
cluster of a synthetic 30 ms scene (``make_scene``, 180 x 240), its
events subsampled to ``n``, evaluated in the whole sensor or in a crop around a corner of the scene (as
discovery's regions are); the three forms alternate, ``--repeats`` times each, and the medians are
printed in microseconds with their ratio. One torch thread (``--threads``), ``OMP_WAIT_POLICY=PASSIVE``.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_fit_eval.py [--repeats 200]
"""

import argparse
import statistics
import time

import numpy as np
import torch

from evseg_torch.events import EventBatch, to_torch
from evseg_torch.kernels.fit import loss_and_grad
from evseg_torch.level_two.image.splat import extent_mask
from evseg_torch.level_two.image.warp import LinearWarp
from evseg_torch.level_two.objectives.contrast import (
    MIN_AREA,
    warped_contrast_loss,
    warped_contrast_loss_and_grad,
)
from evseg_torch.synthetic import make_scene

SIZE = (180, 240)
# (label, events, crop (H, W) or None for the whole sensor)
CASES = (
    ("4k events, whole sensor", 4000, None),
    ("40k events, whole sensor", 40000, None),
    ("1.2k events, 116 x 53 crop", 1200, (53, 116)),
    ("300 events, 52 x 30 crop", 300, (30, 52)),
)


def make_case(n_events: int, crop: tuple[int, int] | None):
    """The arguments of both evaluations for one cluster."""
    scene = make_scene(SIZE, 0.03, n_objects=2, n_events=max(n_events, 40000), rng=0)
    events = to_torch(scene.events)
    keep = torch.ones(len(events), dtype=torch.bool)
    height, width = crop or SIZE
    if crop is not None:
        keep = (events.xy[:, 0] < width - 4) & (events.xy[:, 1] < height - 4) & (events.xy >= 4).all(dim=1)
    chosen = torch.nonzero(keep)[:, 0]
    chosen = chosen[torch.randperm(len(chosen), generator=torch.Generator().manual_seed(0))[:n_events]]
    own = EventBatch(events.xy[chosen][None], events.t[chosen][None], events.p[chosen][None])
    model = scene.motions[0].model
    params = torch.as_tensor(scene.motions[0].params, dtype=torch.float32)[None] * 0.9
    warp = LinearWarp.build(model, own, with_area=True)
    weights = torch.ones(1, len(chosen))
    extent = np.array([[height, width]], dtype=np.int64)
    seed = -torch.ones(1)
    torch_args = (warp, params, weights, (height, width), "variance", 1.0, 0.375, None)
    mask = extent_mask(torch.as_tensor(extent), (height, width))

    def by_autograd():
        leaf = params.clone().requires_grad_()
        loss = warped_contrast_loss(warp, leaf, *torch_args[2:], torch.as_tensor(extent))
        return loss, torch.autograd.grad(loss.sum(), leaf)[0]

    return {
        "autograd": by_autograd,
        "torch": lambda: warped_contrast_loss_and_grad(*torch_args, mask),
        "numba": lambda: loss_and_grad(warp, params, weights, extent, 1.0, 0.375, MIN_AREA, seed),
    }, len(chosen)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); medians of {args.repeats}, µs")
    print(
        f"{'case':<30} {'events':>7} {'autograd':>9} {'torch':>9} {'numba':>9} "
        f"{'torch/autograd':>15} {'numba/torch':>12}"
    )
    for label, n_events, crop in CASES:
        forms, n = make_case(n_events, crop)
        forms["numba"]()  # compiles (or loads the compiled loop) once
        times = {name: [] for name in forms}
        for _ in range(args.repeats):
            for name, run in forms.items():
                start = time.perf_counter()
                run()
                times[name].append(time.perf_counter() - start)
        median = {name: statistics.median(values) * 1e6 for name, values in times.items()}
        print(
            f"{label:<30} {n:>7} {median['autograd']:>9.0f} {median['torch']:>9.0f} {median['numba']:>9.0f} "
            f"{median['torch'] / median['autograd']:>15.2f} {median['numba'] / median['torch']:>12.2f}"
        )


if __name__ == "__main__":
    main()
