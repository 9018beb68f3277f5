"""Quality floors of the whole pipeline on scenes the project did not design, and on the 'hard' family.

Each floor is a mean over many scenes, a few points under the value measured when it was set (see
the README's results); noise and ambiguous events are left out, as the probe's README prescribes.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from evseg_torch.evaluation.labelled import evaluate_labelled
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.pipeline import CascadedSegmenter

PROBE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "synthetic_probe"
# Measured with the default config (the data term's sigma 0.7, label cost 6000), means over pipeline
# seeds 0-8: accuracy 0.944, IMO IoU 0.819, detection 0.894, |count error| 0.148; single seeds 0.930-0.964,
# 0.796-0.839, 0.847-0.938, 0.04-0.29 (seed 0, which this test runs: 0.964, 0.839, 0.917, 0.04). Float
# rounding alone (the same sums in another order) moves a seed's figures by 0.01-0.04, so the floors sit
# under the worst seed. The bars (0.93, 0.80, 0.93, 0.25) are met but for detection.
PROBE_FLOORS = {"accuracy": 0.9, "iou": 0.77, "detection": 0.83, "abs_count_error": 0.35}
# Measured on seeds 0-19 of the 'hard' family, pipeline seeds 0-8: accuracy 0.935, IMO IoU 0.644,
# detection 0.715 (single seeds 0.922-0.940, 0.613-0.666, 0.658-0.767).
FAMILY_FLOORS = {"accuracy": 0.9, "iou": 0.6, "detection": 0.63}


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.skipif(not PROBE.is_dir(), reason="../shared/data/synthetic_probe is not beside the repository")
def test_probe_scenes():
    scores = evaluate_labelled(sorted(PROBE.glob("scene_*.npz")), None)
    assert len(scores) == 24
    accuracy = np.mean([s.accuracy for s in scores])
    iou = np.mean([s.iou for s in scores])
    detection = np.mean([s.detection for s in scores])
    abs_count = np.mean([abs(s.count_error) for s in scores])
    assert accuracy >= PROBE_FLOORS["accuracy"], accuracy
    assert iou >= PROBE_FLOORS["iou"], iou
    assert detection >= PROBE_FLOORS["detection"], detection
    assert abs_count <= PROBE_FLOORS["abs_count_error"], abs_count


def test_hard_family():
    summary = summarize(evaluate_synthetic(CascadedSegmenter((180, 240)), range(20), family="hard"))
    for name, floor in FAMILY_FLOORS.items():
        assert summary[name] >= floor, (name, summary[name])
