import numpy as np
import pytest

from evseg_torch.level_two.energy.label_cost import label_cost, motion_label_costs
from evseg_torch.motion import make_motion_model

SIZE = (180, 240)
MOTION = make_motion_model("translation", SIZE)
WHOLE = [0.0, 0.0, 239.0, 179.0]


def _costs(models, boxes, background=0):
    return motion_label_costs(
        np.asarray(models, dtype=float),
        np.asarray(boxes, dtype=float),
        background,
        100.0,
        0.25,
        duration=0.01,
        motion=MOTION,
        sensor_size=SIZE,
    )


def test_label_cost_scales_with_dense_windows():
    assert label_cost(5000, 6000.0, 15000.0) == 6000.0
    assert label_cost(30000, 6000.0, 15000.0) == 12000.0
    assert label_cost(30000, 6000.0, None) == 6000.0


def test_objects_of_one_motion_pay_it_once():
    # Labels 1 and 2 move alike (0.5 px apart over 10 ms) and lie apart; label 3 moves otherwise.
    models = [[0.0, 0.0], [0.0, 300.0], [50.0, 300.0], [300.0, 0.0]]
    boxes = [WHOLE, [10, 10, 10, 10], [60, 50, 10, 10], [90, 20, 10, 10]]
    costs, groups, group_cost = _costs(models, boxes)
    assert groups.tolist() == [-1, 0, 0, -1]
    np.testing.assert_allclose(costs, [100.0, 25.0, 25.0, 100.0])
    np.testing.assert_allclose(group_cost, [75.0])


def test_an_object_and_the_cluster_that_held_it_with_another_share():
    # Label 1 holds two objects (labels 2 and 3 inside its box), all with one motion.
    models = [[0.0, 0.0], [0.0, 300.0], [0.0, 300.0], [0.0, 300.0]]
    boxes = [WHOLE, [10, 10, 60, 20], [12, 12, 10, 10], [55, 15, 10, 10]]
    _, groups, _ = _costs(models, boxes)
    assert groups.tolist() == [-1, 0, 0, 0]


def test_parts_of_one_object_and_the_backgrounds_motion_pay_in_full():
    # Labels 1 and 2 overlap without either holding the other: two parts of one object. Label 3 moves
    # like the background.
    models = [[0.0, 0.0], [0.0, 300.0], [0.0, 300.0], [10.0, 0.0], [0.0, 310.0]]
    boxes = [WHOLE, [10, 10, 20, 20], [25, 20, 20, 20], [100, 100, 10, 10], [150, 20, 10, 10]]
    costs, groups, group_cost = _costs(models, boxes)
    assert groups.tolist() == [-1, -1, -1, -1, -1] and len(group_cost) == 0
    np.testing.assert_allclose(costs, 100.0)


@pytest.mark.parametrize("n_labels", [1, 2])
def test_a_label_alone_pays_the_full_cost(n_labels):
    costs, groups, group_cost = _costs(np.zeros((n_labels, 2)), [WHOLE] * n_labels)
    assert (groups == -1).all() and len(group_cost) == 0
    np.testing.assert_allclose(costs, 100.0)
