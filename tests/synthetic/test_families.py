from functools import cache

import numpy as np
import pytest
from scipy.ndimage import binary_dilation, binary_erosion

from evseg_torch.errors import ConfigError
from evseg_torch.synthetic import make_scene
from evseg_torch.synthetic.families import KINDS, family_kinds, make_family_scene

SIZE = (180, 240)
WINDOW = 0.03


@cache
def hard(seed, duration=WINDOW):
    return make_family_scene("hard", seed, SIZE, duration)


def seeds_of(kind, count=3):
    return [s for s in range(60) if kind in family_kinds("hard", s)][:count]


def seconds(scene):
    return (scene.events["t"] - scene.t0_us) * 1e-6


def mean_relative_displacement(scene, label, other, t_s):
    """Mean |v_label - v_other| over the label's visible pixels at t_s, times 30 ms."""
    ys, xs = np.nonzero(scene.label_image_at(t_s) == label)
    pixels = np.column_stack([xs, ys]).astype(np.float64)
    mine, theirs = scene.motions[label], scene.motions[other]
    relative = mine.model.velocity(pixels, mine.params) - theirs.model.velocity(pixels, theirs.params)
    return float(np.linalg.norm(relative, axis=1).mean() * WINDOW)


def speed_at_centroid(scene, label, t_s):
    ys, xs = np.nonzero(scene.label_image_at(t_s) == label)
    motion = scene.motions[label]
    return float(np.linalg.norm(motion.model.velocity(np.array([[xs.mean(), ys.mean()]]), motion.params)))


def test_the_seed_cycles_through_the_kinds_and_mixes_them():
    assert [family_kinds("hard", s)[0] for s in range(8)] == [*KINDS, *KINDS]
    kinds = [family_kinds("hard", s) for s in range(60)]
    assert sum(len(k) == 1 for k in kinds) == 20 and all(len(set(k)) == len(k) for k in kinds)
    mixed = {frozenset(k) for k in kinds if len(k) == 2}
    assert frozenset({"similar", "small_fast"}) not in mixed and len(mixed) >= 5
    with pytest.raises(ConfigError):
        family_kinds("easy", 0)
    with pytest.raises(ConfigError):
        make_family_scene("hard", -1)


def test_same_seed_same_scene_and_different_seed_different_scene():
    first, again = hard(5), make_family_scene("hard", 5, SIZE)
    np.testing.assert_array_equal(first.events, again.events)
    np.testing.assert_array_equal(first.labels, again.labels)
    np.testing.assert_array_equal(first.ambiguous, again.ambiguous)
    for a, b in zip(first.motions, again.motions, strict=True):
        np.testing.assert_array_equal(a.params, b.params)
    other = hard(17)  # the same kinds, another seed
    assert family_kinds("hard", 17) == family_kinds("hard", 5)
    assert not np.allclose(other.motions[0].params, first.motions[0].params)


def test_every_scene_has_a_similarity_camera_and_affine4_layers():
    for seed in range(8):
        scene = hard(seed)
        assert all(m.model.name == "affine4" for m in scene.motions)
        v_x, v_y, divergence, rotation = scene.motions[0].params
        assert 20 <= np.hypot(v_x, v_y) <= 120 and abs(rotation) <= 0.6 and abs(divergence) <= 0.3
        assert np.all(np.bincount(scene.labels[scene.labels > 0], minlength=scene.n_objects + 1)[1:] > 100)


@pytest.mark.parametrize("seed", seeds_of("similar"))
def test_similar_objects_move_4_to_6_px_apart_and_5_to_9_px_from_the_background(seed):
    scene = hard(seed)
    assert 2 <= scene.n_objects <= 3
    mid = scene.duration / 2
    for label in range(1, scene.n_objects + 1):
        # Masks and the draw's pixel sample differ slightly at the border.
        assert 5.0 - 0.15 <= mean_relative_displacement(scene, label, 0, mid) <= 9.0 + 0.15
        for other in range(1, label):
            assert 4.0 - 1e-6 <= mean_relative_displacement(scene, label, other, mid) <= 6.0 + 1e-6
    # A shared rotation and scale rate: relative motions between objects are translations.
    np.testing.assert_array_equal(*[m.params[2:] for m in scene.motions[1:3]])


def test_spinning_objects_rotate_and_scale_about_their_own_centres():
    rates = []
    for seed in seeds_of("spinning", 4):
        scene = hard(seed)
        for label in range(1, scene.n_objects + 1):
            divergence, rotation = scene.motions[label].params[2:]
            assert abs(rotation) <= 2.0 and abs(divergence) <= 0.5
            rates.append((abs(rotation), abs(divergence)))
            if not {"similar", "small_fast"} & set(family_kinds("hard", seed)):
                # Its own centre moves at 80-260 px/s (the mask centroid is near it).
                assert 70 <= speed_at_centroid(scene, label, scene.duration / 2) <= 275
    rotation, divergence = np.array(rates).T
    assert rotation.max() > 1.0 and divergence.max() > 0.25  # beyond the mild spin of the other kinds


@pytest.mark.parametrize("seed", seeds_of("small_fast"))
def test_small_fast_objects_in_sparse_windows(seed):
    scene = hard(seed)
    assert 2000 <= len(scene.events) <= 3000 and 1 <= scene.n_objects <= 2
    counts = np.bincount(scene.labels[scene.labels > 0], minlength=scene.n_objects + 1)[1:]
    assert np.all((counts >= 150) & (counts <= 400)), counts
    mid = scene.duration / 2
    extents = scene.boxes_at(mid)[:, 2:] + 1  # pixels across the visible masks
    assert np.all((extents >= 8) & (extents <= 20)), extents
    for label in range(1, scene.n_objects + 1):
        assert 390 <= speed_at_centroid(scene, label, mid) <= 1310


def test_weak_objects_fire_mostly_at_their_outlines():
    inner_share = {True: [], False: []}
    for seed in range(12):
        scene = make_family_scene("hard", seed, (90, 120))
        if "small_fast" in family_kinds("hard", seed):
            continue
        weak = "weak" in family_kinds("hard", seed)
        mid = scene.duration / 2
        near = np.abs(seconds(scene) - mid) < 0.002
        masks, frame = scene.masks_at(mid), scene.log_intensity_at(mid)
        for label in range(1, scene.n_objects + 1):
            inner = binary_erosion(masks[label - 1], iterations=3)
            mine = near & (scene.labels == label)
            inner_share[weak].append(inner[scene.events["y"][mine], scene.events["x"][mine]].mean())
            if weak and inner.sum() > 10:
                assert frame[inner].std() < 0.05  # low-contrast inner texture
    assert max(inner_share[True]) < 0.1 < np.mean(inner_share[False])


def test_ambiguous_events_are_the_background_an_object_uncovers():
    # An object moves 10 px right over a background moving 4 px left and 2 down: the pixels it leaves
    # keep firing with the background's texture.
    params = [np.array([-200.0, 100.0]), np.array([500.0, 0.0])]
    scene = make_scene(
        (64, 80), 0.02, 1, motion_model="translation", layer_params=params, n_events=20000, rng=2
    )
    # Each event's mask at the nearest of 41 times (the object moves 0.25 px between them).
    times = np.linspace(0.0, 0.02, 41)
    masks = np.array([scene.masks_at(t_s)[0] for t_s in times])
    nearest = np.rint(seconds(scene) / 0.0005).astype(np.int64)
    x, y = scene.events["x"], scene.events["y"]
    signal = scene.labels >= 0
    # The anti-aliased border is about 2 px wide, and flags look at the end of a frame interval (0.5 px).
    inside = binary_erosion(masks, iterations=2, structure=np.ones((1, 3, 3)))[nearest, y, x]
    near_now = binary_dilation(masks, iterations=1, structure=np.ones((1, 3, 3)))[nearest, y, x]
    left = signal & binary_erosion(masks[0], iterations=1)[y, x] & ~near_now
    elsewhere = signal & ~binary_dilation(masks.any(axis=0), iterations=1)[y, x]
    assert min(left.sum(), inside.sum(), elsewhere.sum()) >= 100
    assert scene.ambiguous[left].all()
    assert not scene.ambiguous[inside].any() and not scene.ambiguous[elsewhere].any()
    assert not scene.ambiguous[scene.labels < 0].any()


def test_a_shorter_ambiguity_window_flags_fewer_events():
    options = {"sensor_size": (90, 120), "duration": 0.06, "n_objects": 2, "n_events": 8000, "rng": 3}
    whole, recent = make_scene(**options), make_scene(**options, ambiguity_window=0.01)
    np.testing.assert_array_equal(whole.events, recent.events)
    assert not np.any(recent.ambiguous & ~whole.ambiguous)
    assert 0 < recent.ambiguous.sum() < whole.ambiguous.sum()


def test_ambiguous_share_is_like_the_probe():
    shares = [hard(seed).ambiguous.mean() for seed in range(8)]
    assert 0.03 < np.mean(shares) < 0.12 and max(shares) < 0.2


@pytest.mark.parametrize("seed", [0, 2])
def test_long_scenes_keep_the_kind_and_the_objects_in_view(seed):
    scene, window = hard(seed, 0.3), hard(seed)
    assert scene.n_objects == window.n_objects
    per_window = np.bincount(((scene.events["t"] - scene.t0_us) // 30_000).clip(max=9), minlength=10)
    assert 0.5 * len(window.events) < per_window.min() and per_window.max() < 1.5 * len(window.events)
    areas = np.array([scene.masks_at(t_s).sum(axis=(1, 2)) for t_s in np.linspace(0.0, 0.3, 7)])
    assert np.all(areas >= 0.5 * areas[3]), areas  # at least half of each object in view all along
