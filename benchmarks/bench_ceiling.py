"""The true-model ceiling of level two: the pipeline started from each scene's true motions.

Level one is skipped (``level_one.initial_models: replace``) and level two starts from the true model of
every layer (background and objects), then labels, refits, discovers (``discovery_rounds`` rounds, as in a
cold window) and resolves objects as usual,
scored as ``evseg evaluate synthetic`` (our scenes) and ``evseg evaluate labelled`` (the probe) score,
with the objects missed for each reason (:func:`~evseg_torch.evaluation.metrics.object_outcomes`).
The gap to the pipeline's own figures is what level one's pool costs; what remains is the energy's own
limit. Our generator's scenes carry their motions in the project's convention (the ``hard`` family and
the default scenes). The probe's motions are given about each layer's own centre; they are moved to the
view centre (:func:`true_layers`).

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_ceiling.py [--hard 0-59] [--own 0-19] \
        [--set objects=false]
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from bench_quality import add_overrides  # the benchmarks' one KEY=VALUE option (run as a script)

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.evaluation.labelled import load_labelled, score_labelling
from evseg_torch.evaluation.metrics import OUTCOMES
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.events import to_torch
from evseg_torch.level_two.objectives.contrast import contrast_loss
from evseg_torch.pipeline import CascadedSegmenter

PROBE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "synthetic_probe"


def probe_scores(segmenter: CascadedSegmenter, config: SegmenterConfig) -> list:
    """Each probe scene segmented from its layers' true models."""
    scores = []
    model = segmenter.level_two.model
    for path in sorted(PROBE.glob("*.npz")):
        events, labels, ignore, size = load_labelled(path)
        truth = np.where(ignore, -1, labels)
        layers = [int(layer) for layer in np.unique(truth) if layer >= 0]
        models = true_layers(model, events, truth, layers, np.load(path)["motions"], size, config)
        result = segmenter(events, initial_models=models)
        xy = np.column_stack([events["x"], events["y"]])
        scores.append(score_labelling(result.labels, labels, xy, ignore=ignore, n_layers=len(layers)))
    return scores


def true_layers(model, events, truth, layers, motions, size, config) -> np.ndarray:
    """Each layer's true motion as an affine4 model about the view centre :math:`(L, 4)`.

    The probe's similarity motion is moved from the layer's centre (the view's for the background, the
    mean of its events for an object) to the view centre, with the sign of rotation that compensates the
    layer's own events more sharply (the probe's convention is not written down).
    """
    batch = to_torch(events)
    weights = torch.stack([torch.as_tensor(truth == layer, dtype=batch.xy.dtype) for layer in layers])
    centre = np.array([(size[1] - 1) / 2, (size[0] - 1) / 2])
    xy = np.column_stack([events["x"], events["y"]])
    starts = []
    for sign in (1.0, -1.0):
        rows = []
        for layer in layers:
            vx, vy, omega, scale = motions[layer]
            own = centre if layer == 0 else xy[truth == layer].mean(axis=0)
            spin = np.array([[scale, -sign * omega], [sign * omega, scale]])
            rows.append([*(np.array([vx, vy]) + spin @ (centre - own)), scale, sign * omega])
        starts.append(np.array(rows))
    candidates = torch.as_tensor(np.concatenate(starts), dtype=batch.xy.dtype)
    loss = contrast_loss(
        model, batch, candidates, weights.repeat(2, 1), sensor_size=size, sigma=config.level_two.sigma
    )
    best = loss.view(2, len(layers)).argmin(dim=0).numpy()
    return np.stack(starts)[best, np.arange(len(layers))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hard", type=seed_range, default=list(range(60)), help="hard-family seeds")
    parser.add_argument("--own", type=seed_range, default=list(range(20)), help="default-scene seeds")
    add_overrides(parser, "flat config override, e.g. objects=false")
    args = parser.parse_args()
    set_threads(1)
    config = replace_config(SegmenterConfig(), initial_models="replace", **dict(args.set))
    # The true models are given, so the pipeline would treat the window as one that carries models in; the
    # ceiling is that of a cold window's level two, so it runs the same discovery rounds.
    rounds = dict(args.set).get("carried_discovery_rounds", config.level_two.discovery_rounds)
    config = replace_config(config, carried_discovery_rounds=rounds)
    segmenter = CascadedSegmenter((180, 240), config)
    header = f"{'set':<6} {'accuracy':>8} {'IoU':>6} {'detect':>6} {'|count|':>7}"
    print(f"{header}   missed: {' '.join(OUTCOMES[1:])}")
    sets = [("hard", "hard", args.hard), ("own", None, args.own)]
    for name, family, seeds in sets:
        s = summarize(evaluate_synthetic(segmenter, seeds, family=family, true_models=True))
        _print(name, s)
    if PROBE.is_dir():
        _print("probe", summarize(probe_scores(segmenter, config)))


def _print(name: str, s: dict) -> None:
    scores = f"{s['accuracy']:>8.3f} {s['iou']:>6.3f} {s['detection']:>6.3f} {s['abs_count_error']:>7.2f}"
    misses = " ".join(f"{s[f'missed_{outcome}']:>{len(outcome)}.0f}" for outcome in OUTCOMES[1:])
    print(f"{name:<6} {scores}{'':11}{misses}", flush=True)


if __name__ == "__main__":
    main()
