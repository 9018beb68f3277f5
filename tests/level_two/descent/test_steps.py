"""The descent's transitions: next_step's table, and the paths real windows take through it."""

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from evseg_torch.events import to_torch
from evseg_torch.level_two.descent import segmenter as segmenter_module
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.descent.state import WindowState
from evseg_torch.level_two.descent.steps import Step, next_step
from evseg_torch.level_two.discovery import Discovery, Proposals
from evseg_torch.level_two.objects import ObjectPhase
from evseg_torch.synthetic import make_scene

S = Step


def _state(last, **outcome):
    values = {
        "settled": False,
        "proposed": False,
        "outside_support": False,
        "split_made": False,
        "discoveries_left": 0,
        "objects_on": False,
        "splits_left": 0,
    }
    return SimpleNamespace(last=last, **{**values, **outcome})


@pytest.mark.parametrize(
    ("last", "outcome", "objects", "expected"),
    [
        # The paper's descent: label, refit, label ... until the labels settle.
        (S.LABEL, {}, True, S.REFIT),
        (S.REFIT, {}, True, S.LABEL),
        (S.LABEL, {"settled": True}, False, S.STOP),
        # Discovery once settled, while rounds are left; its proposals are labelled.
        (S.LABEL, {"settled": True, "discoveries_left": 1}, True, S.PROPOSE),
        (S.PROPOSE, {"proposed": True}, True, S.LABEL),
        # A round that proposes nothing ends the window, before the object phase.
        (S.PROPOSE, {"proposed": False, "splits_left": 2}, True, S.STOP),
        # The object phase: the support step once, a labelling where it moved some node's costs.
        (S.LABEL, {"settled": True}, True, S.SUPPORT),
        (S.SUPPORT, {"outside_support": True, "objects_on": True, "splits_left": 2}, True, S.LABEL),
        (S.SUPPORT, {"objects_on": True, "splits_left": 2}, True, S.SPLIT),
        (S.SUPPORT, {"objects_on": True}, True, S.STOP),
        # Then splits while allowed: a split is refitted, none made ends the window.
        (S.LABEL, {"settled": True, "objects_on": True, "splits_left": 1}, True, S.SPLIT),
        (S.LABEL, {"settled": True, "objects_on": True, "splits_left": 0}, True, S.STOP),
        (S.SPLIT, {"split_made": True, "objects_on": True, "splits_left": 1}, True, S.REFIT),
        (S.SPLIT, {"objects_on": True, "splits_left": 1}, True, S.STOP),
        # A labelling that has not settled is refitted first, in the object phase too.
        (S.LABEL, {"objects_on": True, "splits_left": 1}, True, S.REFIT),
    ],
)
def test_next_step(last, outcome, objects, expected):
    assert next_step(_state(last, **outcome), objects) is expected


def _trace(monkeypatch, config, seed=1):
    """Segment one synthetic window from its true motions, slightly off, and record its path: the
    steps it takes, in order (the first a labelling; each later one as next_step decided it)."""
    path = [S.LABEL]

    def recording(state, objects):
        path.append(next_step(state, objects))
        return path[-1]

    monkeypatch.setattr(segmenter_module, "next_step", recording)
    scene = make_scene((90, 120), 0.03, n_objects=2, rng=seed)
    pool = torch.as_tensor(np.stack([motion.params for motion in scene.motions]), dtype=torch.float32)
    segmenter = GraphCutContrastSegmenter("affine4", (90, 120), **config)
    segmenter(to_torch(scene.events), pool * 1.05)
    return path


def _valid(steps, discovery_rounds, object_splits):
    assert steps[0] is S.LABEL and steps[-1] is S.STOP
    for before, after in itertools.pairwise(steps):
        if before is S.REFIT:
            assert after is S.LABEL
    assert steps.count(S.PROPOSE) <= discovery_rounds
    assert steps.count(S.SUPPORT) <= 1
    assert steps.count(S.SPLIT) <= object_splits


@pytest.mark.parametrize("discovery_rounds", [0, 1, 2])
def test_real_windows_take_valid_paths(monkeypatch, discovery_rounds):
    path = _trace(monkeypatch, {"discovery_rounds": discovery_rounds})
    _valid(path, discovery_rounds, object_splits=2)
    if discovery_rounds == 0:
        assert S.PROPOSE not in path and S.SUPPORT in path  # settled: straight to the object phase


def test_without_objects_the_path_ends_at_a_settled_labelling(monkeypatch):
    path = _trace(monkeypatch, {"discovery_rounds": 0, "objects": False})
    assert S.SUPPORT not in path and S.SPLIT not in path
    assert path[-2:] == [S.LABEL, S.STOP]


def test_a_round_without_proposals_ends_the_window(monkeypatch):
    # Discovery proposing nothing: the window stops after it and the object phase never runs.
    def nothing(self, events, states):
        return [Proposals(state.params.new_zeros(0, state.params.shape[1]), []) for state in states]

    monkeypatch.setattr(Discovery, "propose", nothing)
    supports = []
    monkeypatch.setattr(ObjectPhase, "support_cost", lambda self, state: supports.append(state))
    path = _trace(monkeypatch, {"discovery_rounds": 1})
    assert path[-2:] == [S.PROPOSE, S.STOP]
    assert not supports


def test_the_window_methods_write_what_next_step_reads():
    state = WindowState.__new__(WindowState)
    state.discoveries_left, state.rounds_left, state.new_clusters = 1, 0, None
    state.params = torch.zeros(2, 4)
    state.add_proposals(torch.zeros(0, 4), [])
    assert (state.last, state.proposed, state.discoveries_left) == (S.PROPOSE, False, 0)
    assert next_step(state, True) is S.STOP
    state.add_proposals(torch.ones(1, 4), [np.arange(3)])
    assert state.proposed and state.params.shape == (3, 4) and state.proposed_from == 2
    assert state.rounds_left == 2  # a first round's proposals: labelled, refitted, labelled again
    assert next_step(state, True) is S.LABEL
