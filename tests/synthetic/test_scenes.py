import cv2
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from evseg_torch.errors import ConfigError
from evseg_torch.events import EVENT_DTYPE, as_events
from evseg_torch.events.images import event_counts
from evseg_torch.synthetic import LayerMotion, SyntheticScene, make_scene

MODELS = ["translation", "affine4", "rotation3d"]


def small_scene(**kwargs) -> SyntheticScene:
    options = {"sensor_size": (90, 120), "duration": 0.02, "n_objects": 2, "n_events": 6000, "rng": 0}
    return make_scene(**{**options, **kwargs})


def seconds(scene: SyntheticScene, events: np.ndarray | None = None) -> np.ndarray:
    events = scene.events if events is None else events
    return (events["t"] - scene.t0_us) * 1e-6


def count_image_variance(xy: np.ndarray, sensor_size, margin: int = 64) -> float:
    """Variance of the image of warped event counts (nearest pixel) on the sensor plus a margin."""
    height, width = sensor_size
    return float(event_counts(np.asarray(xy) + margin, (height + 2 * margin, width + 2 * margin)).var())


def test_types_and_shapes():
    scene = small_scene()
    n = len(scene.events)
    assert scene.events.dtype == EVENT_DTYPE
    assert scene.labels.dtype == np.int64 and scene.labels.shape == (n,)
    assert scene.ambiguous.dtype == bool and scene.ambiguous.shape == (n,)
    assert scene.sensor_size == (90, 120) and scene.duration == 0.02 and scene.n_objects == 2
    assert len(scene.motions) == 3 and all(isinstance(m, LayerMotion) for m in scene.motions)
    for motion in scene.motions:
        assert motion.model.name == "affine4"
        assert motion.params.dtype == np.float64 and motion.params.shape == (4,)
    assert sorted(scene.depth_order) == [1, 2]
    assert scene.to_array().shape == (n, 4)
    assert scene.log_intensity_at(0.01).shape == (90, 120)
    assert scene.label_image_at(0.01).dtype == np.int64


def test_events_are_canonical_sorted_and_inside_the_window():
    scene = small_scene(t0_us=1_234_567, noise_rate_hz=5.0)
    events = scene.events
    np.testing.assert_array_equal(as_events(events, scene.sensor_size), events)
    assert np.all(np.diff(events["t"]) >= 0)
    assert events["t"].min() >= 1_234_567 and events["t"].max() <= 1_234_567 + 20_000
    assert set(np.unique(events["p"]).tolist()) == {-1, 1}
    assert set(np.unique(scene.labels).tolist()) == {-1, 0, 1, 2}


def test_same_seed_same_scene_and_different_seed_different_scene():
    first, again = small_scene(rng=7), small_scene(rng=np.random.default_rng(7))
    np.testing.assert_array_equal(first.events, again.events)
    np.testing.assert_array_equal(first.labels, again.labels)
    for a, b in zip(first.motions, again.motions, strict=True):
        np.testing.assert_array_equal(a.params, b.params)
    other = small_scene(rng=8)
    assert len(other.events) != len(first.events) or np.any(other.events != first.events)
    assert not np.allclose(other.motions[0].params, first.motions[0].params)


@pytest.mark.parametrize("motion_model", MODELS)
def test_labels_agree_with_the_label_image(motion_model):
    scene = small_scene(motion_model=motion_model, rng=3)
    signal = np.flatnonzero(scene.labels >= 0)
    picked = np.random.default_rng(0).choice(signal, 400, replace=False)
    t = seconds(scene)[picked]
    image_labels = np.array(
        [
            scene.label_image_at(ti)[y, x]
            for ti, x, y in zip(t, scene.events["x"][picked], scene.events["y"][picked], strict=True)
        ]
    )
    assert np.mean(image_labels == scene.labels[picked]) >= 0.95


@pytest.mark.parametrize("motion_model", MODELS)
def test_true_motions_sharpen_each_layer(motion_model):
    scene = make_scene(motion_model=motion_model, n_events=25000, rng=11)
    xy = np.column_stack([scene.events["x"], scene.events["y"]]).astype(np.float64)
    t = seconds(scene)
    for label in range(len(scene.motions)):
        mine = scene.labels == label
        variances = [
            count_image_variance(m.model.warp(xy[mine], t[mine], m.params), scene.sensor_size)
            for m in scene.motions
        ]
        assert variances[label] >= 1.2 * count_image_variance(xy[mine], scene.sensor_size)
        assert np.argmax(variances) == label


def test_layers_move_exactly_as_their_models_warp():
    # Integer displacements make bilinear resampling exact, so masks and frames must shift exactly:
    # over 10 ms the background moves by (-2, 1) px and the object by (5, 0) px.
    scene = make_scene(
        (64, 80),
        0.02,
        1,
        motion_model="translation",
        layer_params=[np.array([-200.0, 100.0]), np.array([500.0, 0.0])],
        rng=2,
    )
    mask0, mask1 = scene.masks_at(0.0)[0], scene.masks_at(0.01)[0]
    assert mask1.sum() > 100
    np.testing.assert_array_equal(mask1[:, 5:], mask0[:, :-5])
    frame0, frame1 = scene.log_intensity_at(0.0), scene.log_intensity_at(0.01)
    # Pixels of partial coverage below the label threshold still blend the object in.
    near_object = binary_dilation(mask1, iterations=2) | binary_dilation(
        np.roll(mask0, (1, -2), axis=(0, 1)), iterations=2
    )
    region = ~near_object
    region[0, :] = region[:, -2:] = False  # their source pixels lie outside the sensor
    np.testing.assert_allclose(frame1[region], np.roll(frame0, (1, -2), axis=(0, 1))[region], atol=1e-5)


def test_masks_and_boxes():
    scene = small_scene(n_objects=3, rng=5)
    for t in (0.0, 0.01, 0.02):
        labels, masks, boxes = scene.label_image_at(t), scene.masks_at(t), scene.boxes_at(t)
        assert masks.shape == (3, 90, 120) and masks.dtype == bool and boxes.shape == (3, 4)
        assert masks.sum(axis=0).max() <= 1
        for k in range(3):
            np.testing.assert_array_equal(masks[k], labels == k + 1)
            if not masks[k].any():
                assert np.all(np.isnan(boxes[k]))
                continue
            ys, xs = np.nonzero(masks[k])
            np.testing.assert_array_equal(boxes[k], [xs.min(), ys.min(), np.ptp(xs), np.ptp(ys)])
            near = (scene.labels == k + 1) & (np.abs(seconds(scene) - t) < 1e-3)
            if near.sum() >= 20:
                x, y, w, h = boxes[k]
                ex, ey = scene.events["x"][near], scene.events["y"][near]
                inside = (ex >= x - 1) & (ex <= x + w + 1) & (ey >= y - 1) & (ey <= y + h + 1)
                assert inside.mean() >= 0.9


def test_given_object_shapes_are_where_the_objects_are_at_mid_scene():
    square = np.array([[20.0, 20.0], [50.0, 20.0], [50.0, 50.0], [20.0, 50.0]])
    triangle = np.array([[70.0, 30.0], [100.0, 70.0], [60.0, 70.0]])
    scene = small_scene(object_shapes=[square, triangle])
    for mask, polygon in zip(scene.masks_at(0.01), [square, triangle], strict=True):
        drawn = np.zeros((90, 120), dtype=np.uint8)
        cv2.fillPoly(drawn, [np.rint(polygon).astype(np.int32)], 1)
        union = mask | (drawn > 0)
        assert (mask & (drawn > 0)).sum() / union.sum() > 0.85


def test_an_object_that_left_the_sensor_has_no_box():
    scene = make_scene((64, 80), 0.01, 1, layer_params=[None, np.array([2000.0, 0.0, 0.0, 0.0])], rng=1)
    assert np.all(np.isfinite(scene.boxes_at(0.005)[0]))
    assert np.all(np.isnan(scene.boxes_at(1.0)[0]))
    assert not scene.masks_at(1.0).any()


def test_noise_events_are_labelled_minus_one():
    rate = 40.0
    scene = small_scene(noise_rate_hz=rate, rng=4)
    expected = rate * 90 * 120 * 0.02
    noise = scene.labels == -1
    assert abs(noise.sum() - expected) < 5 * np.sqrt(expected)
    assert 0.4 < np.mean(scene.events["p"][noise] == 1) < 0.6
    assert not np.any(small_scene(noise_rate_hz=0.0, rng=4).labels == -1)


@pytest.mark.parametrize("n_objects", [0, 1, 2, 3])
@pytest.mark.parametrize("motion_model", MODELS)
def test_every_layer_produces_events(n_objects, motion_model):
    scene = small_scene(n_objects=n_objects, motion_model=motion_model, rng=n_objects)
    counts = np.bincount(scene.labels + 1, minlength=n_objects + 2)
    assert len(counts) == n_objects + 2
    assert np.all(counts[1:] > 50), counts
    assert all(m.model.name == motion_model for m in scene.motions)


def test_objects_may_use_other_models_than_the_background():
    scene = small_scene(n_objects=2, object_motion_models=["translation", "rotation3d"])
    assert [m.model.name for m in scene.motions] == ["affine4", "translation", "rotation3d"]
    assert [m.params.shape for m in scene.motions] == [(4,), (2,), (3,)]


@pytest.mark.parametrize("sensor_size", [(64, 80), (180, 240), (40, 200)])
def test_sensor_sizes(sensor_size):
    scene = make_scene(sensor_size, n_objects=1, n_events=8000, rng=0)
    assert scene.events["x"].max() < sensor_size[1] and scene.events["y"].max() < sensor_size[0]
    assert scene.label_image_at(0.0).shape == sensor_size
    assert np.isfinite(scene.boxes_at(scene.duration / 2)[0]).all()


@pytest.mark.parametrize("n_events", [5000, 20000])
def test_event_count_follows_the_request(n_events):
    for seed in range(3):
        scene = small_scene(n_events=n_events, noise_rate_hz=0.0, rng=seed)
        assert 0.8 * n_events < len(scene.events) < 1.2 * n_events


def test_lower_threshold_gives_more_events():
    few = small_scene(n_events=None, contrast_threshold=0.4, rng=6)
    many = small_scene(n_events=None, contrast_threshold=0.2, rng=6)
    assert len(many.events) > 1.5 * len(few.events)
    assert few.contrast_threshold == 0.4


def test_motions_respect_the_speed_constraints():
    scene = small_scene(n_objects=3, rng=9, speed_range=(300.0, 600.0), min_relative_speed=200.0)
    for motion in scene.motions:
        assert motion.params.shape == (4,)
    speeds = [np.hypot(*m.params[:2]) for m in scene.motions]
    assert all(300.0 <= s <= 600.0 for s in speeds)


def test_given_layer_parameters_are_kept():
    params = [np.array([100.0, 0.0]), None, np.array([0.0, -700.0])]
    scene = small_scene(motion_model="translation", layer_params=params)
    np.testing.assert_array_equal(scene.motions[0].params, params[0])
    np.testing.assert_array_equal(scene.motions[2].params, params[2])
    assert np.linalg.norm(scene.motions[1].params - params[0]) >= 200.0


def test_long_scenes_keep_objects_in_view():
    scene = make_scene((64, 80), 0.5, 1, n_events=5000, rng=3)
    assert np.isfinite(scene.boxes_at(0.25)[0]).all()
    assert np.abs(scene.motions[1].params[:2]).max() <= 1500.0 * 80 / 240 * 0.2


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_objects": -1},
        {"n_objects": 1.5},
        {"sensor_size": (0, 80)},
        {"sensor_size": (64,)},
        {"sensor_size": (64.5, 80)},
        {"sensor_size": "big"},
        {"duration": 0.0},
        {"duration": -0.01},
        {"duration": float("nan")},
        {"contrast_threshold": 0.0, "n_events": None},
        {"contrast_threshold": 0.2},
        {"n_events": 0},
        {"threshold_jitter": -0.1},
        {"noise_rate_hz": -1.0},
        {"n_time_steps": 0},
        {"motion_model": "homography"},
        {"object_motion_models": ["affine4"]},
        {"object_motion_models": ["affine4", "spline"]},
        {"layer_params": [None, None]},
        {"layer_params": [np.zeros(2), None, None]},
        {"object_size": (0.2, 0.1)},
        {"speed_range": (-1.0, 10.0)},
        {"speed_range": (0.0, 0.0)},
        {"min_relative_speed": -5.0},
        {"t0_us": -1},
        {"t0_us": 1.5},
        {"object_shapes": [np.zeros((4, 2))]},
        {"object_shapes": [np.zeros((2, 2)), np.zeros((4, 2))]},
        {"object_shapes": [np.zeros((4, 3)), np.zeros((4, 2))]},
        {"object_texture_contrast": 1.5},
        {"object_texture_contrast": -0.1},
        {"background_density": 0.0},
        {"ambiguity_window": 0.0},
    ],
)
def test_invalid_arguments_raise_config_error(kwargs):
    with pytest.raises(ConfigError):
        small_scene(**kwargs)
