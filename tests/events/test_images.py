import numpy as np
import pytest

from evseg_torch.errors import EventFormatError, ShapeError
from evseg_torch.events.images import event_counts


def test_single_image_counts_events_per_pixel_x_column_y_row():
    xy = np.array([[2, 0], [2, 0], [0, 1]])
    image = event_counts(xy, (2, 3))
    assert image.dtype == np.int64 and image.shape == (2, 3)
    np.testing.assert_array_equal(image, [[0, 0, 2], [1, 0, 0]])


def test_float_positions_round_to_nearest_pixel_halves_to_even():
    xy = np.array([[0.4, 0.4], [0.6, 1.4], [1.5, 0.0], [2.5, 0.0], [-0.4, 0.0]])
    np.testing.assert_array_equal(event_counts(xy, (2, 4)), [[2, 0, 2, 0], [0, 1, 0, 0]])


def test_positions_outside_or_not_finite_are_dropped():
    xy = np.array(
        [
            [1.0, 1.0],
            [-0.6, 0.0],
            [3.0, 0.0],
            [0.0, 2.0],
            [0.0, -1.0],
            [np.nan, 0.0],
            [np.inf, 1.0],
            [1e30, 0],
        ]
    )
    image = event_counts(xy, (2, 3))
    assert image.sum() == 1 and image[1, 1] == 1
    np.testing.assert_array_equal(event_counts(np.array([[-1, 0], [0, 5]]), (2, 3)), np.zeros((2, 3)))


def test_label_stack_splits_the_counts_by_label():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2, 12, (500, 2))
    labels = rng.integers(0, 3, 500)
    stack = event_counts(xy, (8, 10), labels)
    assert stack.shape == (3, 8, 10) and stack.dtype == np.int64
    for k in range(3):
        np.testing.assert_array_equal(stack[k], event_counts(xy[labels == k], (8, 10)))
    np.testing.assert_array_equal(stack.sum(axis=0), event_counts(xy, (8, 10)))


def test_labels_outside_range_are_dropped_and_n_labels_sets_the_stack():
    xy = np.array([[0, 0], [1, 0], [1, 0], [0, 1]])
    stack = event_counts(xy, (2, 2), np.array([-1, 1, 1, 3]), n_labels=2)
    np.testing.assert_array_equal(stack, [[[0, 0], [0, 0]], [[0, 2], [0, 0]]])
    assert event_counts(xy, (2, 2), np.array([0, 0, 0, 4])).shape == (5, 2, 2)
    bools = event_counts(xy, (2, 2), np.array([True, False, False, True]))
    np.testing.assert_array_equal(bools, [[[0, 2], [0, 0]], [[1, 0], [1, 0]]])


def test_empty_input():
    empty = np.zeros((0, 2))
    np.testing.assert_array_equal(event_counts(empty, (2, 3)), np.zeros((2, 3)))
    assert event_counts(empty, (2, 3), np.zeros(0, dtype=np.int64)).shape == (0, 2, 3)
    assert event_counts(empty, (2, 3), np.zeros(0, dtype=np.int64), n_labels=2).sum() == 0
    assert event_counts(empty, (2, 3), np.zeros(0, dtype=np.int64), n_labels=2).shape == (2, 2, 3)


def test_bad_arguments_raise():
    with pytest.raises(ShapeError, match="xy"):
        event_counts(np.zeros((4, 3)), (2, 2))
    with pytest.raises(ShapeError, match="labels"):
        event_counts(np.zeros((4, 2)), (2, 2), np.zeros(3, dtype=np.int64))
    with pytest.raises(ShapeError, match="labels"):
        event_counts(np.zeros((4, 2)), (2, 2), np.zeros(4))
    with pytest.raises(EventFormatError, match="sensor_size"):
        event_counts(np.zeros((4, 2)), (0, 2))
