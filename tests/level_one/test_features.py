import numpy as np
import pytest
from scipy import ndimage

from evseg_torch.errors import ConfigError, EventFormatError, ModelError, ShapeError
from evseg_torch.events import EVENT_DTYPE, as_events
from evseg_torch.level_one.features import (
    Correspondences,
    detect_corners,
    event_image,
    extract_correspondences,
    guided_tracks,
    to_uint8,
    track_features,
)
from evseg_torch.motion import Affine4
from evseg_torch.synthetic import make_scene

SENSOR = (180, 240)


def _texture(rng, shape=SENSOR, sigma=2.0):
    """A smooth random texture with plenty of corners, in [0, 255]."""
    noise = ndimage.gaussian_filter(rng.random(shape), sigma)
    noise -= noise.min()
    return (255.0 * noise / noise.max()).astype(np.float32)


class TestEventImage:
    def test_counts(self):
        rng = np.random.default_rng(0)
        xy = np.column_stack([rng.integers(0, 240, 1000), rng.integers(0, 180, 1000)])
        expected = np.zeros(SENSOR)
        np.add.at(expected, (xy[:, 1], xy[:, 0]), 1)
        image = event_image(xy, SENSOR)
        assert image.dtype == np.float32 and image.shape == SENSOR
        np.testing.assert_array_equal(image, expected)

    def test_float_positions_round_to_nearest_pixel(self):
        image = event_image(np.array([[1.4, 0.6], [1.6, 1.4]]), (3, 3))
        assert image[1, 1] == 1 and image[1, 2] == 1 and image.sum() == 2

    def test_outside_sensor_raises(self):
        with pytest.raises(EventFormatError, match="outside the sensor"):
            event_image(np.array([[240, 3]]), SENSOR)
        with pytest.raises(EventFormatError, match="outside the sensor"):
            event_image(np.array([[3, -1]]), SENSOR)

    def test_bad_input_raises(self):
        with pytest.raises(ShapeError):
            event_image(np.zeros((4, 3)), SENSOR)
        with pytest.raises(EventFormatError, match="NaN"):
            event_image(np.array([[np.nan, 1.0]]), SENSOR)
        with pytest.raises(EventFormatError, match="sensor_size"):
            event_image(np.zeros((1, 2)), (0, 10))


class TestDetectCorners:
    def test_finds_the_corners_of_a_square(self):
        image = np.zeros(SENSOR, dtype=np.float32)
        image[60:110, 80:150] = 1.0  # corners at x in {80, 149}, y in {60, 109}
        corners = detect_corners(image, max_corners=4)
        assert corners.shape == (4, 2) and corners.dtype == np.float64
        truth = np.array([[80, 60], [149, 60], [80, 109], [149, 109]], dtype=float)
        distances = np.linalg.norm(corners[:, None] - truth[None], axis=-1)
        assert np.all(distances.min(axis=0) <= 2.0), corners
        assert np.all(distances.min(axis=1) <= 2.0), corners

    def test_min_distance_max_corners_and_order(self):
        image = _texture(np.random.default_rng(1), sigma=1.0)
        for min_distance, max_corners in [(1, 500), (4, 50), (9, 20)]:
            corners = detect_corners(image, min_distance=min_distance, max_corners=max_corners)
            assert 0 < len(corners) <= max_corners
            gaps = np.abs(corners[:, None] - corners[None]).max(axis=-1)
            np.fill_diagonal(gaps, np.inf)
            assert gaps.min() > min_distance
        few = detect_corners(image, min_distance=4, max_corners=10)
        np.testing.assert_array_equal(few, detect_corners(image, min_distance=4, max_corners=50)[:10])

    def test_quality_level_thresholds(self):
        image = _texture(np.random.default_rng(2), sigma=1.0)
        loose = detect_corners(image, quality_level=0.0, max_corners=10_000)
        strict = detect_corners(image, quality_level=0.3, max_corners=10_000)
        assert 0 < len(strict) < len(loose)
        np.testing.assert_array_equal(strict, loose[: len(strict)])

    def test_flat_image_has_no_corners(self):
        assert detect_corners(np.full(SENSOR, 3.0)).shape == (0, 2)

    def test_bad_input_raises(self):
        image = np.zeros(SENSOR)
        with pytest.raises(ShapeError):
            detect_corners(np.zeros((2, *SENSOR)))
        for kwargs in [{"max_corners": 0}, {"min_distance": 0}, {"quality_level": 1.0}, {"sigma": -1.0}]:
            with pytest.raises(ConfigError):
                detect_corners(image, **kwargs)


class TestTrackFeatures:
    def test_recovers_integer_shift(self):
        base = _texture(np.random.default_rng(3), shape=(200, 260))
        shift = np.array([3, -2])  # (x, y): image1[y, x] = image0[y + 2, x - 3]
        image0, image1 = base[10:190, 10:250], base[12:192, 7:247]
        points = detect_corners(image0, max_corners=100)
        src, dst, keep = track_features(image0, image1, points)
        np.testing.assert_array_equal(src, points)
        assert keep.mean() > 0.9
        # LK's 21 x 21 window is truncated within 10 px of the border, where tracks are less exact.
        interior = keep & np.all((src >= 11) & (src <= np.array([240, 180]) - 12), axis=1)
        assert interior.sum() > 50
        errors = np.linalg.norm(dst[interior] - src[interior] - shift, axis=1)
        assert np.median(errors) < 0.01 and errors.max() < 0.15

    def test_drops_tracks_leaving_the_image_and_unmatched_ones(self):
        rng = np.random.default_rng(4)
        image0 = _texture(rng)
        image1 = np.zeros_like(image0)
        image1[:, :-20] = image0[:, 20:]  # everything moves 20 px left, the right strip is new
        points = np.array([[10.0, 90.0], [100.0, 90.0], [230.0, 90.0]])
        _, dst, keep = track_features(image0, image1, points)
        assert not keep[0]  # leaves the image
        assert keep[1] and np.allclose(dst[1], [80.0, 90.0], atol=0.1)
        assert not keep[2]  # its texture is gone, so the round trip fails

    def test_unrelated_images_lose_most_tracks(self):
        rng = np.random.default_rng(5)
        image0, image1 = _texture(rng, sigma=1.0), _texture(rng, sigma=1.0)
        _, _, keep = track_features(image0, image1, detect_corners(image0, max_corners=100))
        assert keep.mean() < 0.2

    def test_empty_points_and_bad_input(self):
        image = np.zeros(SENSOR)
        src, dst, keep = track_features(image, image, np.zeros((0, 2)))
        assert src.shape == dst.shape == (0, 2) and keep.shape == (0,)
        with pytest.raises(ShapeError):
            track_features(image, np.zeros((10, 10)), np.zeros((1, 2)))
        with pytest.raises(ShapeError):
            track_features(image, image, np.zeros((3,)))
        with pytest.raises(ConfigError):
            track_features(image, image, np.zeros((1, 2)), fb_threshold=0.0)

    def test_to_uint8_clips_hot_pixels(self):
        image = np.zeros(SENSOR, dtype=np.float32)
        image[:100, :100] = 2.0
        # One hot pixel: its blur covers fewer than the 0.5 % brightest of the non-zero pixels.
        image[150, 200] = 1000.0
        frame = to_uint8(image)
        assert frame.dtype == np.uint8 and frame[150, 200] == 255 and frame[0, 0] == 255
        assert to_uint8(np.zeros(SENSOR)).max() == 0


class TestGuidedTracks:
    """A 12 px shift, beyond what Lucas-Kanade without a pyramid follows from a zero guess."""

    SHIFT = np.array([12.0, -5.0])

    def _pair(self):
        base = _texture(np.random.default_rng(6), shape=(200, 270))
        image0, image1 = base[10:190, 10:250], base[5:185, 22:262]  # image1 = image0 moved by SHIFT
        points = detect_corners(image0, max_corners=150)
        inside = np.all((points >= 25) & (points <= np.array([215, 155])), axis=1)
        return image0, image1, points[inside]

    def test_initial_guess_replaces_the_pyramid(self):
        image0, image1, points = self._pair()
        _, _, keep = track_features(image0, image1, points, max_level=0)
        assert keep.mean() < 0.2  # no pyramid, no guess: LK stays stuck near the start
        src, dst, keep = track_features(
            image0, image1, points, max_level=0, initial=points - self.SHIFT + 1.0
        )
        assert keep.mean() > 0.9
        np.testing.assert_allclose(dst[keep] - src[keep], np.tile(-self.SHIFT, (keep.sum(), 1)), atol=0.05)

    def test_picks_the_right_candidate(self):
        image0, image1, points = self._pair()
        right, wrong = points - self.SHIFT + 0.7, points + self.SHIFT
        for candidates in (np.stack([wrong, right]), np.stack([right, wrong])):
            src, dst, keep = guided_tracks(image0, image1, points, candidates)
            assert keep.mean() > 0.9
            np.testing.assert_allclose(
                dst[keep] - src[keep], np.tile(-self.SHIFT, (keep.sum(), 1)), atol=0.05
            )

    def test_unexplained_points_are_tracked_cold(self):
        image0, image1, points = self._pair()
        src, dst, keep = guided_tracks(image0, image1, points, (points + self.SHIFT)[None])
        cold = track_features(image0, image1, points)
        assert keep.mean() > 0.9 and keep.sum() >= cold.keep.sum() - 2
        # A random texture may hold a patch that the wrong guess matches both ways, hence 95 %.
        right = np.linalg.norm(dst[keep] - src[keep] + self.SHIFT, axis=1) < 0.05
        assert right.mean() >= 0.95

    def test_bad_input(self):
        image0, image1, points = self._pair()
        with pytest.raises(ShapeError):
            guided_tracks(image0, image1, points, points)
        with pytest.raises(ShapeError):
            guided_tracks(image0, image1, points, np.zeros((0, len(points), 2)))
        with pytest.raises(ShapeError, match="same shape"):
            guided_tracks(image0, image1[:-1], points, points[None])
        # A diverged model's guesses, far outside the image or not finite, only fail like any bad guess.
        for wild in (1e30, np.inf, np.nan):
            _, _, keep = guided_tracks(image0, image1, points, np.full((1, len(points), 2), wild))
            assert keep.mean() > 0.9
        with pytest.raises(ShapeError):
            track_features(image0, image1, points, initial=points[:-1])
        with pytest.raises(ShapeError):
            track_features(image0, image1, points, initial=np.full_like(points, np.nan))
        src, dst, keep = guided_tracks(image0, image1, points[:0], np.zeros((2, 0, 2)))
        assert src.shape == dst.shape == (0, 2) and keep.shape == (0,)


def _events(xy, t_us):
    data = np.empty(len(t_us), dtype=EVENT_DTYPE)
    data["t"], data["x"], data["y"], data["p"] = t_us, xy[:, 0], xy[:, 1], 1
    return data


class TestExtractCorrespondences:
    def test_bad_input_raises(self):
        rng = np.random.default_rng(6)
        events = _events(rng.integers(0, 100, (50, 2)), np.arange(50) * 100)
        with pytest.raises(EventFormatError, match="non-empty"):
            extract_correspondences(events[:0], SENSOR)
        with pytest.raises(EventFormatError, match="outside the sensor"):
            extract_correspondences(events, (50, 50))
        with pytest.raises(EventFormatError, match="sensor_size"):
            extract_correspondences(events, (180,))
        with pytest.raises(EventFormatError, match="canonical"):
            extract_correspondences(np.zeros((50, 4)), SENSOR)
        with pytest.raises(EventFormatError, match="two different times"):
            extract_correspondences(_events(np.zeros((5, 2), dtype=int), np.full(5, 7)), SENSOR)
        for kwargs in [{"sub_window": 0.0}, {"sub_window": 0.6}, {"sub_window_ms": -1.0}]:
            with pytest.raises(ConfigError):
                extract_correspondences(events, SENSOR, **kwargs)

    def test_times_follow_the_sub_windows(self):
        rng = np.random.default_rng(7)
        t_us = np.linspace(1_000, 31_000, 3000).astype(np.int64)
        events = _events(rng.integers(0, 100, (3000, 2)), t_us)
        before = events.copy()
        default = extract_correspondences(events, SENSOR)
        np.testing.assert_array_equal(events, before)
        # At a constant event rate the images' mean event times are their sub-windows' middles, to
        # within the 10 us between events.
        close = {"abs": 1e-5}
        assert (default.t_src, default.t_dst) == pytest.approx((0.005, 0.025), **close)
        shifted = extract_correspondences(events, SENSOR, t_ref=0)
        assert (shifted.t_src, shifted.t_dst) == pytest.approx((0.006, 0.026), **close)
        short = extract_correspondences(events, SENSOR, sub_window_ms=5.0)
        assert (short.t_src, short.t_dst) == pytest.approx((0.0025, 0.0275), **close)
        capped = extract_correspondences(events, SENSOR, sub_window_ms=100.0)
        assert (capped.t_src, capped.t_dst) == pytest.approx((0.0075, 0.0225), **close)
        for result in (default, shifted, short, capped):
            assert result.src.shape == result.dst.shape == (len(result), 2)
            np.testing.assert_allclose(result.dt, result.t_dst - result.t_src)

    def test_times_are_the_mean_event_times(self):
        # A burst near the end of the first third pulls the early image's time towards it.
        rng = np.random.default_rng(8)
        t_us = np.concatenate([np.linspace(1_000, 31_000, 3000), np.full(1000, 10_000)])
        t_us = np.sort(t_us).astype(np.int64)
        result = extract_correspondences(_events(rng.integers(0, 100, (4000, 2)), t_us), SENSOR, t_ref=0)
        assert result.t_src == pytest.approx(1e-6 * t_us[t_us < 11_000].mean())
        assert result.t_dst == pytest.approx(1e-6 * t_us[t_us > 21_000].mean())
        assert result.t_src > 0.0075 and result.t_dst == pytest.approx(0.026, abs=1e-5)


@pytest.mark.realdata
def test_real_recording_yields_consistent_tracks(real_data):
    archive = np.load(real_data / "eed_occlusions" / "events.npz")
    raw = np.empty(archive["t_us"].shape[0], dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    raw["t"], raw["x"], raw["y"], raw["p"] = archive["t_us"], archive["x"], archive["y"], archive["p"]
    sensor = (int(archive["height"]), int(archive["width"]))
    events = as_events(raw, sensor)
    window = events[(events["t"] >= 120_000) & (events["t"] < 150_000)]  # camera pans left, 30 ms
    result = extract_correspondences(window, sensor)
    assert isinstance(result, Correspondences) and len(result) >= 20
    # Round trips measured here, on images rebuilt from the default thirds of the window.
    t, third = window["t"], (int(window["t"][-1]) - int(window["t"][0])) / 3.0
    xy = np.column_stack([window["x"], window["y"]])
    early = to_uint8(event_image(xy[t < t[0] + third], sensor))
    late = to_uint8(event_image(xy[t > t[-1] - third], sensor))
    _, back, _ = track_features(late, early, result.dst)
    round_trip = np.linalg.norm(back - result.src, axis=1)
    assert np.median(round_trip) < 0.25 and round_trip.max() <= 1.0 + 1e-3
    # The camera's ego-motion explains most tracks: trimmed least-squares fits of one similarity motion.
    model = Affine4(sensor)
    flow = result.dst - result.src
    inliers = np.linalg.norm(flow - np.median(flow, axis=0), axis=1) < 1.5
    for _ in range(3):
        estimate = model.from_estimate(result.src[inliers], result.dst[inliers], result.dt[inliers])
        inliers = estimate.residuals(result.src, result.dst, result.dt) < 1.5
    assert inliers.mean() > 0.7


def _exact_track(model, params, src, t_src, t_dst, iterations=30):
    """Where points at ``src`` at ``t_src`` are at ``t_dst`` in a synthetic scene, without approximation.

    A layer's texture point ``u`` is at ``x`` at time ``t`` when ``x - t v(x) = u``; the fixed-point
    iteration converges because ``t |dv/dx|`` is far below 1. ``model.predict`` would be first order
    and here off by up to about 2 px, more than the tolerance.
    """
    texture = src - t_src * model.velocity(src, params)
    position = src.copy()
    for _ in range(iterations):
        position = texture + t_dst * model.velocity(position, params)
    return position


def _agreement(scene, result, radius=3):
    """Whether each track ends within 1.5 px of where the true motion of a layer at its start takes it.

    The layers visible within ``radius`` px of a track's start all count: a corner on an occluding
    silhouette is made of both layers' events, and the label image cannot tell which it follows.
    """
    agree = np.zeros(len(result), dtype=bool)
    for label in range(len(scene.motions)):
        agree |= _agreement_with(scene, result, label, radius)
    return agree


def _agreement_with(scene, result, label, radius=3):
    """:func:`_agreement` with layer ``label`` alone."""
    labels = scene.label_image_at(result.t_src)
    rows, cols = np.rint(result.src[:, 1]).astype(int), np.rint(result.src[:, 0]).astype(int)
    motion = scene.motions[label]
    near = ndimage.binary_dilation(labels == label, np.ones((2 * radius + 1,) * 2))[rows, cols]
    truth = _exact_track(motion.model, motion.params, result.src, result.t_src, result.t_dst)
    return near & (np.linalg.norm(result.dst - truth, axis=1) < 1.5)


def test_tracks_follow_true_motions():
    """Ten synthetic scenes of ~40k events in 30 ms, background and two objects in affine4 motion.

    The speeds are capped at 600 px/s: faster, a 10 ms sub-window smears corners over more than
    6 px and LK tracks on count images lose their precision.
    """
    rates, counts = [], []
    for seed in range(10):
        scene = make_scene(
            SENSOR, 0.03, 2, n_events=40_000, speed_range=(120.0, 600.0), min_relative_speed=120.0, rng=seed
        )
        result = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us)
        counts.append(len(result))
        rates.append(_agreement(scene, result).mean())
    # The bar: 90 % of the kept tracks within 1.5 px of their layer's motion, while the
    # defaults still keep every corner the images offer (small objects need every track).
    assert min(counts) >= 150, counts
    assert np.average(rates, weights=counts) >= 0.9 and min(rates) >= 0.85, np.round(rates, 3)


def test_late_image_corners_add_tracks():
    scene = make_scene(SENSOR, 0.03, 2, speed_range=(100.0, 600.0), min_relative_speed=150.0, rng=3)
    both = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us)
    early = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us, both_images=False)
    assert len(both) >= 1.5 * len(early)
    # The early image's tracks come first and are unchanged; the late ones duplicate none of them: no
    # late corner lies within the default min_distance (2 px) of a forward track's end.
    np.testing.assert_array_equal(both.src[: len(early)], early.src)
    gaps = np.linalg.norm(both.dst[len(early) :, None] - early.dst[None], axis=-1)
    assert gaps.min() > 2.0


def test_guided_tracking_follows_the_previous_motions():
    """Scenes of the track-accuracy test, guided by their true motions 5 % off (a previous window's)."""
    rates, cold_rates, counts = [], [], []
    for seed in range(5):
        scene = make_scene(
            SENSOR, 0.03, 2, n_events=40_000, speed_range=(120.0, 600.0), min_relative_speed=120.0, rng=seed
        )
        params = np.stack([motion.params for motion in scene.motions])
        params *= 1 + np.random.default_rng(seed).normal(0, 0.05, params.shape)
        guide = {"motion": scene.motions[0].model, "initial_models": params}
        guided = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us, **guide)
        cold = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us)
        counts.append((len(guided), len(cold)))
        rates.append(_agreement(scene, guided).mean())
        cold_rates.append(_agreement(scene, cold).mean())
    guided_count, cold_count = np.sum(counts, axis=0)
    assert guided_count >= 0.9 * cold_count, counts
    assert np.mean(rates) >= 0.9 and np.mean(rates) >= np.mean(cold_rates) - 0.01, (rates, cold_rates)


def test_guided_tracking_still_tracks_a_motion_it_lacks():
    """An object whose motion the guide lacks (one that just appeared) keeps most of its cold tracks."""
    guided_count, cold_count = 0, 0
    for seed in range(5):
        scene = make_scene(
            SENSOR, 0.03, 2, n_events=40_000, speed_range=(120.0, 600.0), min_relative_speed=120.0, rng=seed
        )
        known = np.stack([motion.params for motion in scene.motions[:2]])  # object 2 is new
        guide = {"motion": scene.motions[0].model, "initial_models": known}
        guided = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us, **guide)
        cold = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us)
        guided_count += _agreement_with(scene, guided, 2).sum()
        cold_count += _agreement_with(scene, cold, 2).sum()
    assert guided_count >= 0.7 * cold_count, (guided_count, cold_count)


def test_guided_tracking_bad_input():
    events = make_scene(SENSOR, 0.03, 1, rng=0).events
    model = Affine4(SENSOR)
    with pytest.raises(ConfigError, match="motion"):
        extract_correspondences(events, SENSOR, initial_models=np.zeros((1, 4)))
    with pytest.raises(ModelError, match="initial_models"):
        extract_correspondences(events, SENSOR, motion=model, initial_models=np.zeros((1, 3)))
    # No models at all: every corner is tracked cold, as without a guide.
    cold = extract_correspondences(events, SENSOR)
    empty = extract_correspondences(events, SENSOR, motion=model, initial_models=np.zeros((0, 4)))
    np.testing.assert_array_equal(cold.dst, empty.dst)
