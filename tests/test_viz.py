import numpy as np
import pytest

from evseg_torch.errors import EvsegError
from evseg_torch.level_one.features import Correspondences
from evseg_torch.pipeline import Segmentation
from evseg_torch.viz import (
    PALETTE,
    UNLABELLED,
    boxes_figure,
    count_image,
    fig1_figure,
    label_colors,
    render_labels,
    save_figure,
)


def test_label_colors_are_fixed_and_grey_for_unlabelled():
    colours = label_colors(np.array([0, 1, -1, 10]))
    np.testing.assert_array_equal(colours[0], PALETTE[0])
    np.testing.assert_array_equal(colours[2], UNLABELLED)
    np.testing.assert_array_equal(colours[3], PALETTE[0])


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


@pytest.mark.parametrize("ground_truth", [None, np.array([0, 1, 1])])
def test_fig1_panels(tmp_path, ground_truth):
    events = np.zeros(3, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1")])
    events["x"], events["y"] = [1, 2, 3], [1, 1, 2]
    tracks = Correspondences(np.array([[1.0, 1.0]]), np.array([[2.0, 1.0]]), np.array([0.01]), 0.0, 0.01)
    segmentation = Segmentation(
        labels=np.array([0, 1, 1]),
        models=np.zeros((2, 2)),
        motion_model="translation",
        warped_xy=np.array([[1.0, 1], [2, 1], [3, 2]]),
        t_ref=0.0,
        feature_tracks=tracks,
        feature_labels=np.array([0]),
        level_one_models=np.zeros((1, 2)),
        iwes=np.zeros((2, 4, 5)),
        soft_assignments=np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]),
        energy_history=(1.0,),
        timings_ms={},
        sensor_size=(4, 5),
        events=events,
    )
    fig = fig1_figure(segmentation, title="t", metrics={"accuracy": 1.0}, ground_truth=ground_truth)
    assert len(fig.axes) == (4 if ground_truth is None else 5)
    assert save_figure(fig, tmp_path / "f.png").stat().st_size > 1000


def test_boxes_figure(tmp_path):
    image = np.full((20, 30, 3), 255, dtype=np.uint8)
    panels = [
        {
            "image": image,
            "gt_box": np.array([2.0, 3, 5, 4]),
            "predicted_box": np.array([3.0, 3, 5, 4]),
            "title": "a",
        },
        {
            "image": image,
            "gt_box": np.array([2.0, 3, 5, 4]),
            "predicted_box": np.full(4, np.nan),
            "title": "b",
        },
    ]
    fig = boxes_figure(panels, title="EED", columns=5)
    drawn = [ax for ax in fig.axes if ax.images]
    assert len(drawn) == 2 and [len(ax.patches) for ax in drawn] == [2, 1]  # no box where none matched
    assert drawn[1].get_title() == "b"
    assert save_figure(fig, tmp_path / "boxes.png").stat().st_size > 1000
    with pytest.raises(EvsegError, match="at least one panel"):
        boxes_figure([])
