"""Named families of seeded synthetic scenes, built with :func:`evseg_torch.synthetic.make_scene`.

The ``hard`` family covers the failure modes we know of. Seed ``s`` has the kind ``KINDS[s % 4]``, alone
when ``s // 4 % 3 == 0`` and otherwise mixed with one of its two partners (:func:`family_kinds`):

* ``similar``: 2-3 objects whose motions differ from each other's by 4-6 px over a 30 ms window and
  from the background's by 5-9 px (on average over the object's pixels); the objects share one rotation
  and scale rate, so their relative motions are uniform translations;
* ``spinning``: objects rotating by up to ±2 rad/s and scaling by up to ±0.5 /s about their own centres;
* ``small_fast``: 1-2 balls 8-20 px across at 400-1300 px/s, in sparse windows of 2-3k events (like the
  two balls of EED's "occlusions");
* ``weak``: objects whose inner texture has 5-15% of the usual contrast, so that mostly their outlines
  fire.

As in ``shared/data/synthetic_probe``, the camera always moves by a similarity (translation 20-120 px/s,
rotation up to ±0.6 rad/s, scale rate up to ±0.3 /s about the view centre), objects 43-77 px across
move at 80-260 px/s about their own centres (``similar`` and ``small_fast`` aside), every layer moves at
least 2.5 px relative to every other over 30 ms, and objects that do not spin still rotate by up to
±0.5 rad/s and scale by up to ±0.15 /s. The background's texture is 6 times as dense as
:func:`~evseg_torch.synthetic.make_scene`'s and the contrast threshold 0.12 ±10% per pixel, so that a
window holds about as many events as a probe window (15-45k), about two thirds of them the background's.

Sizes, speeds and displacements are for a sensor 240 px wide and scale with ``max(H, W)``; displacements
are per 30 ms *window*, so a longer scene (a stream) keeps the motions of a window, except that an
object's speed is capped so that its centre, which starts in the middle 60% of the view, travels at
most 40% of the sensor's shorter side over the scene, and stays in view.

Examples:
    >>> scene = make_family_scene("hard", 2)
    >>> family_kinds("hard", 2), scene.n_objects, 2000 < len(scene.events) < 3000
    (('small_fast',), 2, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from evseg_torch.errors import ConfigError
from evseg_torch.motion import MotionModel, make_motion_model
from evseg_torch.synthetic.checks import check_positive, check_scene_size
from evseg_torch.synthetic.draws import object_shape
from evseg_torch.synthetic.scenes import SyntheticScene, make_scene
from evseg_torch.validation import check_integer

__all__ = ["FAMILIES", "KINDS", "family_kinds", "make_family_scene"]

FAMILIES = ("hard",)
KINDS = ("similar", "spinning", "small_fast", "weak")
# The second kind mixed into seeds with s // 4 % 3 == 1 and 2 (similar motions exclude fast objects).
_PARTNERS = {
    "similar": ("spinning", "weak"),
    "spinning": ("weak", "similar"),
    "small_fast": ("spinning", "weak"),
    "weak": ("similar", "spinning"),
}
_WINDOW = 0.03  # s: displacements are given over a window this long
_REFERENCE_WIDTH = 240.0  # px: sizes and speeds are for a sensor this wide
_IN_VIEW_TRAVEL = 0.4  # largest travel of an object's centre over a scene, as a fraction of the shorter side
_CANDIDATES = 1000  # motions drawn per object before giving up
_REGION_POINTS = 300  # object pixels over which relative motions are averaged
_CAMERA_SPIN = (0.6, 0.3)  # largest |rotation| rad/s and |scale rate| 1/s of the camera
_STRONG_SPIN, _MILD_SPIN = (2.0, 0.5), (0.5, 0.15)  # the same, of objects
_OBJECT_AREA = (0.03, 0.11)  # fractions of the image: objects 43-77 px across at 180 x 240
# The background's texture is denser than make_scene's, and the contrast threshold lower, so that a
# window holds about as many events, as large a share of them the background's, as the probe's.
_BACKGROUND_DENSITY = 6.0
_THRESHOLD = 0.12
# Sparse windows keep this many signal events in all and per object (30 ms, 240 px wide; they scale with
# the duration and the sensor's area), a random subset of 4 times as many.
_SPARSE_EVENTS, _SPARSE_OBJECT_EVENTS, _OVERSAMPLE = (2300, 2800), (150, 400), 4
_NOISE_FRACTION = 0.025  # noise events per signal event in sparse windows


@dataclass(frozen=True)
class _Recipe:
    """What a scene of the family holds; speeds in px/s and displacements in px per window, at scale 1."""

    n_objects: int
    camera_speed: tuple[float, float]
    object_speed: tuple[float, float] | None  # own-centre speed; None: relative to the previous layer
    spin: tuple[float, float]  # largest |rotation| and |scale rate| of the objects
    to_background: tuple[float, float]
    between_objects: tuple[float, float]
    ball_diameter: tuple[float, float] | None  # balls instead of random shapes of _OBJECT_AREA
    texture_contrast: float
    sparse: bool  # windows of _SPARSE_EVENTS


def family_kinds(family: str, seed: int) -> tuple[str, ...]:
    """The failure modes of a family's scene: its primary kind, then the one mixed in, if any.

    Args:
        family: a name of :data:`FAMILIES`.
        seed: the scene's seed, a non-negative integer.

    Raises:
        ConfigError: unknown family or invalid seed.
    """
    if family not in FAMILIES:
        raise ConfigError(f"unknown scene family {family!r}; choose one of {list(FAMILIES)}")
    seed = check_integer(seed, "seed")
    primary, mix = KINDS[seed % len(KINDS)], seed // len(KINDS) % 3
    return (primary,) if mix == 0 else (primary, _PARTNERS[primary][mix - 1])


def make_family_scene(
    family: str, seed: int, sensor_size: tuple[int, int] = (180, 240), duration: float = 0.03
) -> SyntheticScene:
    """The scene of a family for a seed (see the module docstring).

    Args:
        family: a name of :data:`FAMILIES`.
        seed: a non-negative integer; it picks the kinds (:func:`family_kinds`) and seeds everything else.
        sensor_size: ``(H, W)``.
        duration: seconds; 15-35 ms for one window, longer for a stream of windows of the same kind.

    Returns:
        A :class:`~evseg_torch.synthetic.SyntheticScene` with affine4 layers, whose ``ambiguous`` flags
        look back at most 30 ms.

    Raises:
        ConfigError: an argument is out of its range.
    """
    kinds = family_kinds(family, seed)
    height, width = check_scene_size(sensor_size)
    duration = check_positive(duration, "duration")
    rng = np.random.default_rng(seed)
    scale = max(height, width) / _REFERENCE_WIDTH
    recipe = _recipe(kinds, rng)
    model = make_motion_model("affine4", (height, width))
    if recipe.ball_diameter is None:
        shapes = [object_shape(rng, (height, width), *_OBJECT_AREA) for _ in range(recipe.n_objects)]
    else:
        shapes = [_ball(rng, (height, width), recipe.ball_diameter, scale) for _ in range(recipe.n_objects)]
    view_centre = np.array([model.principal_point])
    camera = _similarity(
        model, view_centre, _velocities(rng, recipe.camera_speed, scale, 1), _spins(rng, 1, _CAMERA_SPIN)
    )
    speed_cap = _IN_VIEW_TRAVEL * min(height, width) / duration
    params = _object_motions(rng, model, camera[0], shapes, recipe, scale, speed_cap)
    windows = duration / _WINDOW * scale**2  # the scene's worth of 30 ms windows of a 240 px wide sensor
    options = {"contrast_threshold": _THRESHOLD}
    if recipe.sparse:
        total = rng.uniform(*_SPARSE_EVENTS) * windows
        noise_rate_hz = _NOISE_FRACTION * total / (height * width * duration)
        options = {"n_events": round(_OVERSAMPLE * total), "noise_rate_hz": noise_rate_hz}
    scene = make_scene(
        (height, width),
        duration,
        recipe.n_objects,
        layer_params=[camera[0], *params],
        object_shapes=shapes,
        object_texture_contrast=recipe.texture_contrast,
        background_density=_BACKGROUND_DENSITY,
        threshold_jitter=0.1,
        ambiguity_window=min(duration, _WINDOW),
        rng=rng,
        **options,
    )
    if not recipe.sparse:
        return scene
    objects = np.rint(rng.uniform(*_SPARSE_OBJECT_EVENTS, recipe.n_objects) * windows).astype(np.int64)
    return _thin(scene, [round(total) - int(objects.sum()), *objects], rng)


def _thin(scene: SyntheticScene, counts, rng) -> SyntheticScene:
    """The scene with a random subset of each layer's events, at most ``counts[k]`` of layer ``k``'s,
    as a sensor that drops events; noise events are all kept."""
    keep = scene.labels < 0
    for label, count in enumerate(counts):
        mine = np.flatnonzero(scene.labels == label)
        keep[rng.choice(mine, min(count, len(mine)), replace=False)] = True
    return replace(
        scene, events=scene.events[keep], labels=scene.labels[keep], ambiguous=scene.ambiguous[keep]
    )


def _recipe(kinds: tuple[str, ...], rng: np.random.Generator) -> _Recipe:
    similar, small_fast = "similar" in kinds, "small_fast" in kinds
    lowest = 2 if similar else 1
    return _Recipe(
        n_objects=int(rng.integers(lowest, 3 if small_fast else 4)),
        camera_speed=(20.0, 120.0),
        object_speed=None if similar else (400.0, 1300.0) if small_fast else (80.0, 260.0),
        spin=_STRONG_SPIN if "spinning" in kinds else _MILD_SPIN,
        to_background=(5.0, 9.0) if similar else (2.5, math.inf),
        between_objects=(4.0, 6.0) if similar else (2.5, math.inf),
        ball_diameter=(6.0, 17.0) if small_fast else None,
        texture_contrast=float(rng.uniform(0.05, 0.15)) if "weak" in kinds else 1.0,
        sparse=small_fast,
    )


def _object_motions(rng, model: MotionModel, camera, shapes, recipe: _Recipe, scale, speed_cap):
    """affine4 parameters of each object, drawn jointly until they meet the recipe's displacements.

    An object either moves at its own speed range, or (``similar``) relative to the layer before it:
    the background for the first object, the previous object for the others, with one rotation and
    scale rate shared by all objects. Every object's displacement over a window relative to every
    earlier layer, averaged over the object's pixels, must lie in ``to_background`` against the
    background and in ``between_objects`` against an object; its centre must move at most at
    ``speed_cap``. Each of :data:`_CANDIDATES` draws sets every object; the first that passes is kept.
    """
    shared = _spins(rng, _CANDIDATES, recipe.spin)
    layers = [camera]
    ok = np.ones(_CANDIDATES, dtype=bool)
    for polygon in shapes:
        centre = polygon.mean(axis=0, keepdims=True)
        if recipe.object_speed is None:
            span = recipe.to_background if len(layers) == 1 else recipe.between_objects
            base = model.velocity(centre, layers[-1]).reshape(-1, 2)
            own = base + _velocities(rng, np.divide(span, _WINDOW), scale, _CANDIDATES)
            spin = shared
        else:
            own = _velocities(
                rng, np.minimum(np.multiply(recipe.object_speed, scale), speed_cap), 1.0, _CANDIDATES
            )
            spin = _spins(rng, _CANDIDATES, recipe.spin)
        candidates = _similarity(model, centre, own, spin)
        region = _interior(polygon, model.sensor_size)
        velocity = model.velocity(region, candidates)
        ok &= np.linalg.norm(own, axis=1) <= speed_cap
        for label, other in enumerate(layers):
            low, high = np.multiply(recipe.to_background if label == 0 else recipe.between_objects, scale)
            moved = np.linalg.norm(velocity - model.velocity(region, other), axis=-1).mean(axis=1) * _WINDOW
            ok &= (moved >= low) & (moved <= high)
        layers.append(candidates)
    if not ok.any():
        raise ConfigError(f"no object motions met the scene family's constraints in {_CANDIDATES} draws")
    return [layer[int(np.argmax(ok))] for layer in layers[1:]]


def _velocities(rng, speeds, scale: float, count: int) -> np.ndarray:
    """``count`` velocities :math:`(count, 2)` of uniform heading and speed in ``scale * speeds``."""
    speed = rng.uniform(speeds[0] * scale, speeds[1] * scale, count)
    heading = rng.uniform(0.0, 2 * np.pi, count)
    return speed[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])


def _spins(rng, count: int, limits) -> np.ndarray:
    """``count`` pairs ``(scale rate, rotation)`` :math:`(count, 2)` uniform within ``±limits``."""
    return np.column_stack(
        [rng.uniform(-limits[1], limits[1], count), rng.uniform(-limits[0], limits[0], count)]
    )


def _similarity(model: MotionModel, centre, own, spin) -> np.ndarray:
    """affine4 parameters :math:`(K, 4)` of similarity motions about ``centre`` :math:`(1, 2)`.

    ``own`` :math:`(K, 2)` is the velocity at the centre and ``spin`` :math:`(K, 2)` the divergence
    (scale rate) and rotation: a rotation and scaling about the centre is one about the principal
    point plus a translation.
    """
    divergence, rotation = spin.T
    offset = centre - np.asarray(model.principal_point)
    linear = np.column_stack(
        [
            divergence * offset[0, 0] - rotation * offset[0, 1],
            rotation * offset[0, 0] + divergence * offset[0, 1],
        ]
    )
    return np.column_stack([own - linear, divergence, rotation])


def _interior(polygon: np.ndarray, sensor_size) -> np.ndarray:
    """Up to :data:`_REGION_POINTS` pixel coordinates :math:`(V, 2)` evenly spread over the polygon's
    pixels on the sensor."""
    mask = np.zeros(sensor_size, dtype=np.uint8)
    cv2.fillPoly(mask, [np.rint(polygon).astype(np.int32)], 1)
    rows, cols = np.nonzero(mask)
    step = max(1, len(rows) // _REGION_POINTS)
    return np.column_stack([cols[::step], rows[::step]]).astype(np.float64)


def _ball(rng, sensor_size, diameters, scale: float) -> np.ndarray:
    """A disc polygon :math:`(32, 2)` of diameter in ``scale * diameters``, centred in the middle 60%."""
    height, width = sensor_size
    radius = 0.5 * scale * rng.uniform(*diameters)
    centre = rng.uniform((0.2 * width, 0.2 * height), (0.8 * width, 0.8 * height))
    angles = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
    return centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])
