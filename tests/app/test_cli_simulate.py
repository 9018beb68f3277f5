"""``evseg simulate``: synthetic scenes written in the probe scenes' layout."""

import numpy as np

from evseg_torch.app.cli import main
from evseg_torch.evaluation.labelled import load_labelled
from evseg_torch.io import load_events
from evseg_torch.synthetic.families import make_family_scene
from tests.helpers.cli import scene_file


def test_simulate_writes_readable_scenes(tmp_path):
    path = scene_file(tmp_path)
    events = load_events(path)
    data = np.load(path)
    assert len(events) == len(data["labels"]) > 1000
    assert (int(data["height"]), int(data["width"])) == (90, 120)
    # The layout of the probe scenes, which `evaluate labelled` reads.
    _, labels, ambiguous, size = load_labelled(path)
    np.testing.assert_array_equal(labels, data["labels"])
    assert size == (90, 120) and ambiguous.dtype == bool and 0 < ambiguous.sum() < 0.2 * len(events)


def test_simulate_writes_a_scene_family(tmp_path):
    assert main(["--quiet", "simulate", "--out", str(tmp_path), "--seeds", "2", "--family", "hard"]) == 0
    scene = make_family_scene("hard", 2)
    events, labels, ambiguous, size = load_labelled(tmp_path / "scene_0002.npz")
    np.testing.assert_array_equal(events, scene.events)
    np.testing.assert_array_equal(labels, scene.labels)
    np.testing.assert_array_equal(ambiguous, scene.ambiguous)
    assert size == (180, 240)
