"""One window's Fig. 1 panels as one RGB image, and as a matplotlib figure."""

import numpy as np
import pytest

from evseg_torch.errors import ShapeError
from evseg_torch.level_one.features import Correspondences
from evseg_torch.pipeline import Segmentation
from evseg_torch.viz.figures import fig1_figure, save_figure
from evseg_torch.viz.panels import PANEL_SIDE, VIDEO_PANELS, render_fig1, write_png
from evseg_torch.viz.render import PALETTE


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
