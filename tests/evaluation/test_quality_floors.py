"""Quality floors of the whole pipeline on scenes the project did not design, on the 'hard' family, and
on the EED recordings.

Each floor is a mean over many scenes, a few points under the value measured when it was set (see
the README's results); noise and ambiguous events are left out, as the probe's README prescribes.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from evseg_torch.config import SegmenterConfig, bundled_config, load_config, replace_config
from evseg_torch.evaluation.eed import detection_rate, evaluate_sequence, load_eed_sequence
from evseg_torch.evaluation.labelled import evaluate_labelled
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.pipeline import CascadedSegmenter

PROBE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "synthetic_probe"
# Measured with the default config (two Progressive-X pools, the data term's sigma 0.65, label cost
# 6000, the compiled fits), means over pipeline seeds 0-2, 3-5 and 6-8: accuracy 0.943 / 0.944 / 0.947, IMO
# IoU 0.802 / 0.822 / 0.830, detection 0.861 / 0.891 / 0.933, |count error| 0.250 / 0.181 / 0.194. Single
# seeds spread wider (detection 0.819-0.972), and float rounding alone moves a 3-seed mean's detection by
# 3-4 points (docs/objects.md), so the test takes seeds 0-2 and its floors sit under the worst triplet.
PROBE_SEEDS = (0, 1, 2)
PROBE_FLOORS = {"accuracy": 0.9, "iou": 0.77, "detection": 0.82, "abs_count_error": 0.35}
# Measured before the two pools on seeds 0-19 of the 'hard' family, pipeline seeds 0-8: accuracy 0.935,
# IMO IoU 0.644, detection 0.715 (single seeds 0.922-0.940, 0.613-0.666, 0.658-0.767).
FAMILY_FLOORS = {"accuracy": 0.9, "iou": 0.6, "detection": 0.63}
# EED (the shipped eed.yaml, seed 0, boxes at the box time): one box under each reading measured
# (nested: 13/14 what_is_background, 6/13 occlusions, 2/14 multiple_objects; I/pred the same but 7/14 on
# multiple_objects, where 3 seeds give 7, 7 and 7 boxes; on the AMD EPYC), two under I/pred there.
EED_FLOORS = {
    "what_is_background": {
        "detection_rate_nested": 100 * 12 / 14,
        "detection_rate_over_predicted": 100 * 12 / 14,
    },
    "occlusions": {"detection_rate_nested": 100 * 5 / 13, "detection_rate_over_predicted": 100 * 5 / 13},
    "multiple_objects_2objs_first_half": {
        "detection_rate_nested": 100 * 1 / 14,
        "detection_rate_over_predicted": 100 * 5 / 14,
    },
}


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.slow
@pytest.mark.skipif(not PROBE.is_dir(), reason="../shared/data/synthetic_probe is not beside the repository")
def test_probe_scenes():
    paths = sorted(PROBE.glob("scene_*.npz"))
    scores = [
        score
        for seed in PROBE_SEEDS
        for score in evaluate_labelled(paths, replace_config(SegmenterConfig(), seed=seed))
    ]
    assert len(scores) == 24 * len(PROBE_SEEDS)
    accuracy = np.mean([s.accuracy for s in scores])
    iou = np.mean([s.iou for s in scores])
    detection = np.mean([s.detection for s in scores])
    abs_count = np.mean([abs(s.count_error) for s in scores])
    assert accuracy >= PROBE_FLOORS["accuracy"], accuracy
    assert iou >= PROBE_FLOORS["iou"], iou
    assert detection >= PROBE_FLOORS["detection"], detection
    assert abs_count <= PROBE_FLOORS["abs_count_error"], abs_count


@pytest.mark.slow
def test_hard_family():
    summary = summarize(evaluate_synthetic(CascadedSegmenter((180, 240)), range(20), family="hard"))
    for name, floor in FAMILY_FLOORS.items():
        assert summary[name] >= floor, (name, summary[name])


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EED_FLOORS))
def test_eed_sequences(real_data, name):
    sequence = load_eed_sequence(real_data / f"eed_{name}")
    rates = detection_rate(evaluate_sequence(sequence, load_config(bundled_config("eed"))))
    for reading, floor in EED_FLOORS[name].items():
        assert rates[reading] >= floor - 1e-9, (reading, rates[reading])
