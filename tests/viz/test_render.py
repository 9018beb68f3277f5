"""Colours of ids and RGB images of events and labels."""

import numpy as np

from evseg_torch.viz.render import PALETTE, UNLABELLED, count_image, label_colors, render_labels


def test_label_colors_are_a_function_of_the_id():
    ids = np.array([0, 1, -1, 10, 11, 10])
    colours = label_colors(ids)
    np.testing.assert_array_equal(colours[0], PALETTE[0])
    np.testing.assert_array_equal(colours[2], UNLABELLED)
    np.testing.assert_array_equal(colours[3], colours[5])
    np.testing.assert_array_equal(label_colors(ids[::-1]), colours[::-1])  # not a function of the order
    beyond = label_colors(np.arange(10, 40))
    assert len({tuple(c) for c in beyond}) == 30 and not any((c == UNLABELLED).all() for c in beyond)


def test_count_image_rounds_and_drops_outside():
    xy = np.array([[0.2, 0.4], [0.0, 0.0], [1.6, 1.0], [9.0, 0.0], [-1.0, 0.0]])
    image = count_image(xy, (2, 3))
    assert image[0, 0] == 2 and image[1, 2] == 1 and image.sum() == 3


def test_render_labels_takes_the_majority_per_pixel():
    xy = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [0.0, 0.0]])
    image = render_labels(xy, np.array([2, 2, 0, -1]), (2, 2))
    np.testing.assert_array_equal(image[1, 1], PALETTE[2])
    np.testing.assert_array_equal(image[0, 0], UNLABELLED)
    np.testing.assert_array_equal(image[0, 1], [255, 255, 255])
