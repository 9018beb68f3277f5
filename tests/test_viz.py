import numpy as np
import pytest

from evseg_torch.errors import EvsegError, ShapeError
from evseg_torch.level_one.features import Correspondences
from evseg_torch.panels import PANEL_SIDE, VIDEO_PANELS, render_fig1, write_png
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


def _segmentation(xy, labels, sensor_size, n_clusters):
    events = np.zeros(len(xy), dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1")])
    events["t"] = np.arange(len(xy)) * 10
    events["x"], events["y"] = np.asarray(xy).T
    start = np.asarray(xy[:1], dtype=float)
    tracks = Correspondences(start, start + np.array([1.0, 0.0]), np.array([0.01]), 0.0, 0.01)
    return Segmentation(
        labels=np.asarray(labels),
        models=np.zeros((n_clusters, 2)),
        motion_model="translation",
        warped_xy=np.asarray(xy, dtype=float),
        t_ref=0.0,
        feature_tracks=tracks,
        feature_labels=np.array([0]),
        level_one_models=np.zeros((1, 2)),
        iwes=np.zeros((n_clusters, *sensor_size)),
        soft_assignments=np.eye(n_clusters)[labels],
        energy_history=(1.0,),
        timings_ms={},
        sensor_size=sensor_size,
        events=events,
    )


@pytest.mark.parametrize("ground_truth", [None, np.array([0, 1, 1])])
def test_fig1_panels(tmp_path, ground_truth):
    segmentation = _segmentation([[1, 1], [2, 1], [3, 2]], [0, 1, 1], (4, 5), 2)
    image = render_fig1(segmentation, title="t", metrics={"accuracy": 1.0}, ground_truth=ground_truth)
    assert image.dtype == np.uint8 and image.ndim == 3
    assert write_png(image, tmp_path / "f.png").stat().st_size > 1000
    fig = fig1_figure(segmentation, title="t", ground_truth=ground_truth)
    assert save_figure(fig, tmp_path / "g.png").stat().st_size > 1000


def _colour_pixels(image, colour):
    return int(np.all(image == colour, axis=2).sum())


def test_fig1_crops_to_the_events_and_colours_by_id():
    # A small active region of a large sensor fills its panels after cropping.
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.integers(600, 640, 400), rng.integers(300, 320, 400)])
    labels = (xy[:, 0] >= 620).astype(int)
    segmentation = _segmentation(xy, labels, (800, 1280), 2)
    cropped = render_fig1(segmentation, panels=("segmented",))
    whole = render_fig1(segmentation, panels=("segmented",), crop=False)
    assert _colour_pixels(cropped, PALETTE[1]) > 20 * _colour_pixels(whole, PALETTE[1]) > 0
    # Colours follow the ids given to the clusters, not the clusters' order.
    relabelled = render_fig1(segmentation, panels=("segmented",), ids=np.array([7, 3]))
    assert _colour_pixels(relabelled, PALETTE[0]) == 0
    assert _colour_pixels(relabelled, PALETTE[7]) > 0 and _colour_pixels(relabelled, PALETTE[3]) > 0
    with pytest.raises(ShapeError, match="ids"):
        render_fig1(segmentation, ids=np.array([1]))


def test_fig1_layout_follows_the_crops_shape():
    wide = _segmentation([[0, 0], [199, 9]], [0, 0], (10, 200), 1)
    tall = _segmentation([[0, 0], [9, 199]], [0, 0], (200, 10), 1)
    # A wide sensor's four panels (400 px wide each) stack in one column, a tall one's (400 px high) line up.
    assert render_fig1(wide, crop=False).shape[1] < 2 * PANEL_SIDE
    assert render_fig1(tall, crop=False).shape[0] < 2 * PANEL_SIDE
    # Video frames: the whole sensor, so one size for every window.
    first = render_fig1(wide, panels=VIDEO_PANELS, crop=False)
    other = render_fig1(
        _segmentation([[5, 5], [6, 5]], [0, 0], (10, 200), 1), panels=VIDEO_PANELS, crop=False
    )
    assert first.shape == other.shape


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
