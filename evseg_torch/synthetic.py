"""Synthetic event scenes with exact ground truth: an ESIM-like generator, the embedded default data.

A scene is a textured background moved by the camera's ego-motion and ``n_objects`` textured
independently moving objects (IMOs) in front of it, each a *layer* with a motion model of
:mod:`evseg_torch.motion` and parameters ``theta``. A layer's log-intensity is

    ``I(x, t) = I0(M.warp(x, t, theta)) = I0(x - t v(x))``,  ``v(x) = M.velocity(x, theta)``,

with ``t`` in seconds from the scene start and ``I0`` the layer's texture at ``t = 0``; an object is
visible at ``x`` when its ``t = 0`` mask covers ``M.warp(x, t, theta)`` (anti-aliased coverage above
5%) and no object in front of it covers ``x``. Hence warping a layer's events with its true parameters,
``model.warp(xy, t - t0, theta)``, maps every event back onto the texture's edges at ``t = 0``: the
ground truth is exactly consistent with the motion models, with no first-order approximation left
between the two.

Events are simulated as in ESIM: log-intensity frames are rendered at ``n_time_steps + 1`` times
(bilinear ``cv2.remap`` of each layer's texture, composited back to front with anti-aliased masks),
and each pixel emits one event per crossing of its contrast threshold between consecutive frames,
timestamped by linear interpolation. An event's label is the front-most layer visible at its pixel in
either frame of its interval (:meth:`SyntheticScene.label_image_at` renders the visible layers): the
events of an object's silhouette, where it covers *or uncovers* the background, move with the
occluding contour and are therefore the object's. An event is *ambiguous*
(:attr:`SyntheticScene.ambiguous`) when its pixel was dominated (covered at least half) earlier in the
window by a layer in front of the one dominating it at the event: background uncovered behind a moving
object, fired by the object's trailing edge, which moves with the object, or by the texture that
reappears there. Its layer is not well defined: benchmarks leave such events out, as the labelled probe
scenes of ``shared/data/synthetic_probe`` flag them.

The number of events grows with the contrast of the textures, the speeds and ``1 / contrast_threshold``:
with the defaults, a 30 ms scene on a 180 x 240 sensor has about 35k to 85k events. Pass ``n_events``
instead of a threshold to get that many signal events within a few percent, whatever the motions (the
threshold is then chosen by a trial simulation of a sparse subset of the pixels).

Examples:
    >>> scene = make_scene((90, 120), duration=0.02, n_objects=1, n_events=5000, rng=0)
    >>> scene.events.dtype.names, scene.labels.shape == scene.events.shape
    (('t', 'x', 'y', 'p'), True)
    >>> [m.model.name for m in scene.motions]
    ['affine4', 'affine4']
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from evseg_torch.errors import ConfigError
from evseg_torch.events import EVENT_DTYPE, to_array
from evseg_torch.motion import MOTION_MODELS, MotionModel, make_motion_model

_REFERENCE_WIDTH = 240.0  # the default speeds are for a sensor this wide; they scale with max(H, W)
_MAX_STEP_PX = 0.5  # largest motion between rendered frames, so that linear interpolation holds
# An object covers a pixel where its anti-aliased coverage exceeds this: then the events of its moving
# silhouette, trailing edge included, are its own, as its motion explains them.
_COVERED = 0.05
_MAX_DIVERGENCE = 1.5  # affine4 divergence and rotation, 1/s
_MAX_ANGULAR = 1.0  # rotation3d angular velocity per axis, rad/s
_FULL_SPEED_DURATION = 0.1  # longer scenes slow every motion down, so objects stay in view
_MASK_SHIFT = 4  # sub-pixel bits of polygon vertices (cv2.fillPoly's shift)
_MAX_DRAWS = 2000  # motion candidates tried per layer before giving up
_COUNT_PIXELS = 3000  # pixels simulated to choose the contrast threshold for a requested event count
_THRESHOLD_SEARCH = (0.01, 2.0)  # range of contrast thresholds searched for a requested event count


@dataclass(frozen=True)
class LayerMotion:
    """The true motion of one layer.

    Attributes:
        model: its motion model (family and sensor geometry).
        params: float64 :math:`(P,)`, in the :mod:`evseg_torch.motion` convention (rates per second,
            coordinates centred on the principal point).
    """

    model: MotionModel
    params: np.ndarray


@dataclass(frozen=True, eq=False)
class _Layer:
    """A layer ready to render: its texture and coverage at ``t = 0``, and its motion on the pixel grid.

    ``image`` is :math:`(h, w)` log intensity for the background, and the premultiplied pair
    ``(alpha, alpha * log intensity)`` :math:`(h, w, 2)` for an object; ``base`` holds the pixel grid
    in the image's coordinates :math:`(2, H, W)` and ``flow`` the layer's velocity there, so that
    ``base - t * flow`` is ``model.warp`` of the grid in image coordinates.
    """

    image: np.ndarray
    base: np.ndarray
    flow: np.ndarray

    def sample(self, t: float) -> np.ndarray:
        # Replicating the border is right for both: the background's texture reaches past all the
        # sensor sees, and an object's image has a transparent border.
        map_x, map_y = self.base - np.float32(t) * self.flow
        return cv2.remap(self.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Events with ground truth, and the scene that made them.

    Attributes:
        events: canonical structured events (:data:`~evseg_torch.events.EVENT_DTYPE`), sorted by
            time, :math:`(N,)`.
        labels: int64 :math:`(N,)`, the true layer of each event: 0 background, ``1..n_objects`` the
            objects, -1 noise.
        ambiguous: bool :math:`(N,)`, events whose pixel was dominated by a layer in front of the one
            dominating it at the event within the preceding ``ambiguity_window`` seconds (see the
            module docstring); False for noise.
        motions: one :class:`LayerMotion` per layer, indexed by label.
        sensor_size: ``(H, W)``.
        t0_us: the scene's start in microseconds; an event's time in the motion convention is
            ``(t - t0_us) * 1e-6`` seconds.
        duration: seconds.
        depth_order: object labels from back to front.
        contrast_threshold: the mean contrast threshold that was used (log units).
    """

    events: np.ndarray
    labels: np.ndarray
    ambiguous: np.ndarray
    motions: tuple[LayerMotion, ...]
    sensor_size: tuple[int, int]
    t0_us: int
    duration: float
    depth_order: tuple[int, ...]
    contrast_threshold: float
    _layers: tuple[_Layer, ...] = field(repr=False)

    @property
    def n_objects(self) -> int:
        return len(self.motions) - 1

    def log_intensity_at(self, t_s: float) -> np.ndarray:
        """The rendered log-intensity frame at ``t_s`` seconds after the start, float32 :math:`(H, W)`."""
        return _render(self._layers, self.depth_order, t_s)[0]

    def label_image_at(self, t_s: float) -> np.ndarray:
        """The visible layer at each pixel at ``t_s`` seconds after the start, int64 :math:`(H, W)`."""
        return _render(self._layers, self.depth_order, t_s)[1]

    def masks_at(self, t_s: float) -> np.ndarray:
        """The visible part of each object at ``t_s``, bool :math:`(K, H, W)`; row ``k`` is label ``k+1``."""
        labels = self.label_image_at(t_s)
        return labels[None] == np.arange(1, self.n_objects + 1)[:, None, None]

    def boxes_at(self, t_s: float) -> np.ndarray:
        """Boxes ``[x, y, w, h]`` of each object's visible pixels at ``t_s``, float64 :math:`(K, 4)`.

        As :func:`evseg_torch.metrics.box_of_points` of the mask's pixel coordinates: ``x, y`` the
        smallest column and row, ``w, h`` the extents. A row is NaN where the object is not visible.
        """
        masks = self.masks_at(t_s)
        boxes = np.full((self.n_objects, 4), np.nan)
        cols, rows = masks.any(axis=1), masks.any(axis=2)
        visible = cols.any(axis=1)
        x_min, y_min = cols.argmax(axis=1), rows.argmax(axis=1)
        x_max = cols.shape[1] - 1 - cols[:, ::-1].argmax(axis=1)
        y_max = rows.shape[1] - 1 - rows[:, ::-1].argmax(axis=1)
        boxes[visible] = np.column_stack([x_min, y_min, x_max - x_min, y_max - y_min])[visible]
        return boxes

    def to_array(self) -> np.ndarray:
        """Events as float64 :math:`(N, 4)` with columns ``[t_seconds, x, y, p]`` (absolute times)."""
        return to_array(self.events)


def make_scene(
    sensor_size: tuple[int, int] = (180, 240),
    duration: float = 0.03,
    n_objects: int = 2,
    *,
    motion_model: str = "affine4",
    object_motion_models: Sequence[str] | None = None,
    layer_params: Sequence[np.ndarray | None] | None = None,
    contrast_threshold: float | None = None,
    n_events: int | None = None,
    threshold_jitter: float = 0.03,
    noise_rate_hz: float = 0.5,
    n_time_steps: int | None = None,
    t0_us: int = 0,
    object_size: tuple[float, float] = (0.03, 0.15),
    speed_range: tuple[float, float] | None = None,
    min_relative_speed: float | None = None,
    object_shapes: Sequence[np.ndarray] | None = None,
    object_texture_contrast: float = 1.0,
    background_density: float = 1.0,
    ambiguity_window: float | None = None,
    rng: np.random.Generator | int | None = None,
) -> SyntheticScene:
    """Simulate the events of a textured scene with moving objects, and keep its ground truth.

    Args:
        sensor_size: ``(H, W)``, each at least 16.
        duration: seconds.
        n_objects: independently moving objects in front of the background, 0 or more.
        motion_model: the background's (camera's) motion model: ``translation``, ``affine4`` or
            ``rotation3d``; also the objects' unless ``object_motion_models`` is given.
        object_motion_models: one model name per object.
        layer_params: optional true parameters per layer (background first), each :math:`(P,)` or
            None to draw it at random.
        contrast_threshold: mean contrast threshold ``C`` in log intensity; defaults to 0.2.
        n_events: about how many signal (non-noise) events to generate; sets the contrast threshold
            from a trial simulation instead, so it excludes ``contrast_threshold``. Scenes land
            within about 10% of it, most within 3%.
        threshold_jitter: relative standard deviation of the per-pixel thresholds
            ``C (1 + jitter N(0, 1))``, fixed per pixel.
        noise_rate_hz: noise events per pixel per second, uniform in space and time, label -1.
        n_time_steps: rendered frame intervals; defaults to the fewest for which no layer moves more
            than half a pixel between frames.
        t0_us: timestamp of the scene's start in microseconds, non-negative.
        object_size: range of each object's area at mid-scene, as a fraction of the image.
        speed_range: range of the layers' mean image speeds in px/s; defaults to ``(100, 600)`` times
            ``max(H, W) / 240``, the speeds of hand-held recordings such as EED and EV-IMO (level one's
            Lucas-Kanade tracks degrade beyond about 600 px/s on a 30 ms window). Divergence and
            rotation rates of affine4 are drawn in +-1.5 1/s and angular velocities of rotation3d in
            +-1 rad/s. For ``duration`` above 0.1 s every default
            range is scaled by ``0.1 / duration``, so that objects stay in view.
        min_relative_speed: least mean speed, over an object's pixels, of its motion relative to the
            background's and to every other object's; defaults to 150 px/s on the same scale.
        object_shapes: optional polygons :math:`(V, 2)` (``x, y`` pixel vertices, ``V >= 3``), one per
            object: where each object is at mid-scene; instead of random shapes of ``object_size``.
        object_texture_contrast: scale of the contrast of the objects' inner texture about their base
            level, in ``[0, 1]``; low values leave mostly the objects' outlines to fire events.
        background_density: how many shapes the background's texture holds per area, relative to the
            default (about one per 650 px).
        ambiguity_window: how far back, in seconds, an occluding layer at an event's pixel makes the
            event ambiguous; defaults to ``duration`` (the scene is one window).
        rng: ``numpy.random.Generator`` or seed; the same seed gives the same scene.

    Returns:
        A :class:`SyntheticScene`.

    Raises:
        ConfigError: an argument is out of its range, or no motions meet the speed constraints.
    """
    height, width = _check_sensor_size(sensor_size)
    duration = _positive(duration, "duration")
    n_objects = _count(n_objects, "n_objects", minimum=0)
    models = _motion_models(motion_model, object_motion_models, n_objects, (height, width))
    given = _layer_params(layer_params, models)
    if contrast_threshold is not None and n_events is not None:
        raise ConfigError("give at most one of contrast_threshold and n_events")
    threshold = 0.2 if contrast_threshold is None else _positive(contrast_threshold, "contrast_threshold")
    if n_events is not None:
        n_events = _count(n_events, "n_events", minimum=1)
    threshold_jitter = _non_negative(threshold_jitter, "threshold_jitter")
    noise_rate_hz = _non_negative(noise_rate_hz, "noise_rate_hz")
    if n_time_steps is not None:
        n_time_steps = _count(n_time_steps, "n_time_steps", minimum=1)
    t0_us = _count(t0_us, "t0_us", minimum=0)
    area_low, area_high = _fraction_range(object_size)
    if object_shapes is not None:
        object_shapes = _polygons(object_shapes, n_objects)
    object_texture_contrast = _non_negative(object_texture_contrast, "object_texture_contrast")
    if object_texture_contrast > 1:
        raise ConfigError(f"object_texture_contrast must be in [0, 1], got {object_texture_contrast}")
    background_density = _positive(background_density, "background_density")
    horizon = duration if ambiguity_window is None else _positive(ambiguity_window, "ambiguity_window")
    slow = min(1.0, _FULL_SPEED_DURATION / duration)
    scale = max(height, width) / _REFERENCE_WIDTH * slow
    speeds = (100.0 * scale, 600.0 * scale) if speed_range is None else _speed_range(speed_range)
    if min_relative_speed is not None:
        min_relative_speed = _non_negative(min_relative_speed, "min_relative_speed")
    min_relative = 150.0 * scale if min_relative_speed is None else min_relative_speed
    rng = np.random.default_rng(rng)

    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1).reshape(-1, 2).astype(float)
    shapes = object_shapes or [
        _object_shape(rng, (height, width), area_low, area_high) for _ in range(n_objects)
    ]
    corners = np.array([[0.0, 0.0], [width - 1.0, height - 1.0]])
    regions = [_grid_around(corners)] + [_grid_around(polygon) for polygon in shapes]
    params = _draw_motions(models, given, regions, speeds, min_relative, slow, rng)

    layers = [
        _background_layer(models[0], params[0], grid, duration, (height, width), background_density, rng)
    ]
    for model, theta, polygon in zip(models[1:], params[1:], shapes, strict=True):
        # The polygon is where the object is at mid-scene; its t = 0 mask is that warped back.
        start = model.warp(polygon, np.full(len(polygon), duration / 2), theta)
        layers.append(_object_layer(model, theta, start, grid, (height, width), object_texture_contrast, rng))
    layers = tuple(layers)
    depth_order = tuple(int(k) + 1 for k in rng.permutation(n_objects))

    if n_time_steps is None:
        fastest = max(float(np.abs(layer.flow).max()) for layer in layers)
        n_time_steps = max(1, math.ceil(fastest * duration / _MAX_STEP_PX))
    times = np.linspace(0.0, duration, n_time_steps + 1)
    if n_events is not None:
        threshold = _threshold_for(layers, depth_order, times, n_events, rng)
    signal = _simulate(layers, depth_order, times, threshold, threshold_jitter, horizon, rng)
    noise = _noise(noise_rate_hz, duration, (height, width), rng)
    t_s, xy, polarity, labels, ambiguous = (np.concatenate(pair) for pair in zip(signal, noise, strict=True))

    order = np.argsort(t_s, kind="stable")
    events = np.empty(len(order), dtype=EVENT_DTYPE)
    events["t"] = t0_us + np.rint(t_s[order] * 1e6).astype(np.int64)
    events["x"], events["y"] = xy[order, 0], xy[order, 1]
    events["p"] = polarity[order]
    motions = tuple(LayerMotion(model, theta) for model, theta in zip(models, params, strict=True))
    return SyntheticScene(
        events=events,
        labels=labels[order].astype(np.int64),
        ambiguous=ambiguous[order],
        motions=motions,
        sensor_size=(height, width),
        t0_us=t0_us,
        duration=duration,
        depth_order=depth_order,
        contrast_threshold=float(threshold),
        _layers=layers,
    )


def _render(layers: tuple[_Layer, ...], depth_order: tuple[int, ...], t: float) -> tuple[np.ndarray, ...]:
    """Composite log intensity :math:`(H, W)` float32 at time ``t``, and two int64 label images: the
    visible layer (the front-most covering more than ``_COVERED`` of a pixel) and the dominant one (the
    front-most covering at least half of it)."""
    frame = layers[0].sample(t)
    labels = np.zeros(frame.shape, dtype=np.int64)
    dominant = np.zeros(frame.shape, dtype=np.int64)
    for label in depth_order:
        alpha, premultiplied = np.moveaxis(layers[label].sample(t), -1, 0)
        frame = frame * (1.0 - alpha) + premultiplied
        labels[alpha > _COVERED] = label
        dominant[alpha >= 0.5] = label
    return frame, labels, dominant


def _threshold_for(layers, depth_order, times, n_events: int, rng) -> float:
    """The contrast threshold that yields about ``n_events`` events.

    Counts the events of a grid of candidate thresholds at once on a sparse subset of the pixels
    (a few thousand, rendered alone, so this costs a fraction of the simulation), then interpolates
    the count, which falls monotonically with the threshold, in log-log scale.
    """
    height, width = layers[0].flow.shape[1:]
    stride = max(1, math.isqrt(height * width // _COUNT_PIXELS))
    every = (slice(None), slice(stride // 2, None, stride), slice(stride // 2, None, stride))
    sparse = tuple(_Layer(layer.image, layer.base[every], layer.flow[every]) for layer in layers)
    candidates = np.geomspace(*_THRESHOLD_SEARCH, 16)[:, None]
    previous = _render(sparse, depth_order, times[0])[0].ravel()
    reference = previous + candidates * rng.uniform(-1.0, 1.0, previous.shape)
    counts = np.zeros(len(candidates))
    for t in times[1:]:
        change = _render(sparse, depth_order, t)[0].ravel() - reference
        crossings = np.floor(np.abs(change) / candidates)
        counts += crossings.sum(axis=1)
        reference += np.sign(change) * crossings * candidates
    counts *= height * width / previous.size
    candidates = candidates[:, 0]
    if counts[0] < n_events or counts[-1] > n_events:
        # Beyond the search range the count scales about as 1 / threshold.
        end = 0 if counts[0] < n_events else -1
        return float(candidates[end] * max(counts[end], 1.0) / n_events)
    # Counts fall with the threshold; np.interp needs increasing abscissae.
    log_counts = np.log(np.maximum(counts[::-1], 1.0))
    return float(np.exp(np.interp(np.log(n_events), log_counts, np.log(candidates[::-1]))))


def _simulate(layers, depth_order, times, threshold, jitter, horizon, rng):
    """ESIM between consecutive frames: one event per threshold crossing, time linearly interpolated.

    Returns times, pixels ``(x, y)``, polarities, labels and the ambiguity flags of the events. An event
    is ambiguous when, within ``horizon`` seconds before it, its pixel was dominated by a layer in
    front of the one dominating it at the end of its interval: uncovered behind an object, from the
    trailing edge's second half on (the leading edge never is).
    """
    previous, previous_labels, dominant = (a.ravel() for a in _render(layers, depth_order, times[0]))
    depth = np.zeros(len(layers), dtype=np.int64)
    depth[np.asarray(depth_order, dtype=np.int64)] = np.arange(1, len(depth_order) + 1)
    everywhere = np.arange(previous.size)
    # When each layer last dominated each pixel.
    last_dominant = np.full((len(layers), previous.size), -np.inf)
    last_dominant[dominant, everywhere] = times[0]
    thresholds = threshold * np.clip(1.0 + jitter * rng.standard_normal(previous.shape), 0.1, None)
    # A random phase of each pixel's reference level, as a sensor running long before the scene has.
    reference = previous + thresholds * rng.uniform(-1.0, 1.0, previous.shape)
    chunks = []
    for t_start, t_end in itertools.pairwise(times):
        frame, frame_labels, dominant = (a.ravel() for a in _render(layers, depth_order, t_end))
        change = frame - reference
        counts = np.floor(np.abs(change) / thresholds).astype(np.int64)
        pixels = np.flatnonzero(counts)
        if pixels.size:
            n = counts[pixels]
            sign = np.sign(change[pixels])
            pixel = np.repeat(pixels, n)
            # The j-th crossing (1-based) of each pixel in this interval.
            j = np.arange(pixel.size) - np.repeat(np.cumsum(n) - n, n) + 1
            level = reference[pixel] + np.repeat(sign, n) * j * thresholds[pixel]
            fraction = np.clip((level - previous[pixel]) / (frame[pixel] - previous[pixel]), 0.0, 1.0)
            before, after = previous_labels[pixel], frame_labels[pixel]
            labels = np.where(depth[after] > depth[before], after, before)
            t = t_start + fraction * (t_end - t_start)
            in_front = depth[:, None] > depth[dominant[pixel]]
            occluded = np.where(in_front, last_dominant[:, pixel], -np.inf).max(axis=0) >= t - horizon
            chunks.append((t, pixel, np.repeat(sign, n), labels, occluded))
            reference[pixels] += sign * n * thresholds[pixels]
        previous, previous_labels = frame, frame_labels
        last_dominant[dominant, everywhere] = t_end
    width = layers[0].flow.shape[2]
    if not chunks:
        empty = np.zeros(0, dtype=np.int64)
        return np.zeros(0), np.zeros((0, 2), dtype=np.int64), empty, empty, np.zeros(0, dtype=bool)
    t_s, pixel, polarity, labels, ambiguous = (np.concatenate(parts) for parts in zip(*chunks, strict=True))
    xy = np.column_stack([pixel % width, pixel // width])
    return t_s, xy, polarity.astype(np.int64), labels, ambiguous


def _noise(rate_hz, duration, sensor_size, rng):
    """Noise events uniform in space and time: times, pixels, polarities, labels (-1) and ambiguity."""
    height, width = sensor_size
    count = rng.poisson(rate_hz * height * width * duration)
    xy = np.column_stack([rng.integers(0, width, count), rng.integers(0, height, count)])
    t_s, polarity = rng.uniform(0.0, duration, count), rng.choice(np.array([-1, 1]), count)
    return t_s, xy, polarity, np.full(count, -1), np.zeros(count, dtype=bool)


def _background_layer(model, theta, grid, duration, sensor_size, density, rng) -> _Layer:
    """A textured log-intensity image covering every point the sensor sees over the scene."""
    flow = model.velocity(grid, theta)
    # warp is linear in t, so the sensor's pixels sweep the texture between t = 0 and t = duration.
    seen = np.concatenate([grid, grid - duration * flow])
    low = np.floor(seen.min(axis=0)) - 3
    size = (np.ceil(seen.max(axis=0)) + 4 - low).astype(int)
    texture = _background_texture(rng, (int(size[1]), int(size[0])), density)
    return _make_layer(texture, low, grid, flow, sensor_size)


def _object_layer(model, theta, polygon, grid, sensor_size, contrast, rng) -> _Layer:
    """An object's premultiplied (alpha, alpha * texture) image around its ``t = 0`` polygon."""
    low = np.floor(polygon.min(axis=0)) - 3
    size = (np.ceil(polygon.max(axis=0)) + 4 - low).astype(int)
    shape = (int(size[1]), int(size[0]))
    coverage = np.zeros(shape, dtype=np.uint8)
    vertices = np.rint((polygon - low) * (1 << _MASK_SHIFT)).astype(np.int32)
    cv2.fillPoly(coverage, [vertices], 255, lineType=cv2.LINE_AA, shift=_MASK_SHIFT)
    alpha = coverage.astype(np.float32) / 255.0
    texture = _object_texture(rng, shape, contrast)
    flow = model.velocity(grid, theta)
    return _make_layer(np.dstack([alpha, alpha * texture]), low, grid, flow, sensor_size)


def _make_layer(image, origin, grid, flow, sensor_size) -> _Layer:
    height, width = sensor_size
    base = (grid - origin).T.reshape(2, height, width).astype(np.float32)
    return _Layer(image=image, base=base, flow=flow.T.reshape(2, height, width).astype(np.float32))


def _background_texture(rng, shape, density: float) -> np.ndarray:
    """Piecewise-constant log intensity of rectangles, bars and lines, with strong edges; about
    ``density`` shapes per 650 px."""
    height, width = shape
    texture = _smooth_noise(rng, shape, cell=24.0, amplitude=0.01)
    n_shapes = max(4, round(height * width / 650 * density))
    kinds = rng.integers(0, 3, n_shapes)
    levels = rng.uniform(-0.5, 0.5, n_shapes)
    centres = rng.uniform((0, 0), (width, height), (n_shapes, 2))
    sizes = rng.uniform(3.0, 20.0, (n_shapes, 2))
    angles = rng.uniform(0, np.pi, n_shapes)
    for kind, level, centre, size, angle in zip(kinds, levels, centres, sizes, angles, strict=True):
        if kind == 2:
            direction = np.array([np.cos(angle), np.sin(angle)]) * size[0] * 1.5
            ends = np.rint([centre - direction, centre + direction]).astype(np.int32)
            cv2.line(texture, tuple(ends[0]), tuple(ends[1]), float(level), thickness=1 + int(size[1]) % 3)
        else:
            aspect = size if kind == 0 else size * (1.0, 0.3)
            box = cv2.boxPoints(((*centre,), (*aspect,), float(np.degrees(angle)) * (kind == 1)))
            cv2.fillPoly(texture, [np.rint(box).astype(np.int32)], float(level))
    return cv2.GaussianBlur(texture, (0, 0), 0.7)


def _object_texture(rng, shape, contrast: float) -> np.ndarray:
    """Blobs of random log intensity on an offset base, unlike the background's rectangles; their
    contrast and that of the base's noise about the base level are scaled by ``contrast``."""
    height, width = shape
    offset = rng.choice([-1, 1]) * rng.uniform(0.3, 0.6)
    texture = _smooth_noise(rng, shape, cell=8.0, amplitude=0.02 * contrast) + np.float32(offset)
    n_blobs = max(3, round(height * width / 650))
    centres = np.rint(rng.uniform((0, 0), (width, height), (n_blobs, 2))).astype(int)
    radii = rng.integers(1, 5, n_blobs)
    levels = offset + contrast * (rng.uniform(-1.0, 1.0, n_blobs) - offset)
    for centre, radius, level in zip(centres, radii, levels, strict=True):
        cv2.circle(texture, (int(centre[0]), int(centre[1])), int(radius), float(level), thickness=-1)
    return cv2.GaussianBlur(texture, (0, 0), 0.7)


def _smooth_noise(rng, shape, cell: float, amplitude: float) -> np.ndarray:
    height, width = shape
    coarse = rng.normal(0.0, amplitude, (math.ceil(height / cell) + 2, math.ceil(width / cell) + 2))
    return cv2.resize(coarse.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)


def _object_shape(rng, sensor_size, area_low, area_high) -> np.ndarray:
    """A random ellipse or star polygon :math:`(V, 2)` of the drawn area, centred in the middle 60%."""
    height, width = sensor_size
    area = rng.uniform(area_low, area_high) * height * width
    if rng.random() < 0.5:
        angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        radii = np.column_stack([np.cos(angles), rng.uniform(0.5, 1.0) * np.sin(angles)])
        turn = rng.uniform(0, np.pi)
        radii = radii @ np.array([[np.cos(turn), np.sin(turn)], [-np.sin(turn), np.cos(turn)]])
    else:
        count = int(rng.integers(5, 10))
        angles = (np.arange(count) + rng.uniform(-0.3, 0.3, count)) * (2 * np.pi / count)
        radii = rng.uniform(0.6, 1.0, count)[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    x, y = radii.T
    radii *= math.sqrt(area / (0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))))
    centre = rng.uniform((0.2 * width, 0.2 * height), (0.8 * width, 0.8 * height))
    return centre + radii


def _grid_around(points: np.ndarray) -> np.ndarray:
    """A 5x5 grid :math:`(25, 2)` over the bounding box of ``points`` :math:`(V, 2)`."""
    low, high = points.min(axis=0), points.max(axis=0)
    axes = [np.linspace(low[i], high[i], 5) for i in range(2)]
    return np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)


def _draw_motions(models, given, regions, speeds, min_relative, slow, rng) -> list[np.ndarray]:
    """Parameters per layer: the given ones, and random ones whose mean speed over the layer's region
    is in ``speeds`` and which differ from every layer already set by at least ``min_relative`` px/s
    on average over that region."""
    params = list(given)
    for label, (model, region) in enumerate(zip(models, regions, strict=True)):
        if params[label] is not None:
            continue
        candidates = _candidates(model, rng, speeds, slow)
        velocity = model.velocity(region, candidates)  # (K, V, 2)
        mean_speed = np.linalg.norm(velocity, axis=-1).mean(axis=1)
        ok = (mean_speed >= speeds[0]) & (mean_speed <= speeds[1])
        for other_model, other in zip(models, params, strict=True):
            if other is not None:
                relative = np.linalg.norm(velocity - other_model.velocity(region, other), axis=-1)
                ok &= relative.mean(axis=1) >= min_relative
        if not ok.any():
            raise ConfigError(
                f"no {model.name} motion of mean speed in {speeds} px/s differing by at least "
                f"{min_relative} px/s from the other layers was found in {_MAX_DRAWS} draws; "
                "widen speed_range or lower min_relative_speed"
            )
        params[label] = candidates[int(np.argmax(ok))]
    return params


def _candidates(model, rng, speeds, slow) -> np.ndarray:
    """``_MAX_DRAWS`` random parameter vectors :math:`(K, P)` of the model's family."""
    speed = rng.uniform(speeds[0], speeds[1], _MAX_DRAWS)
    heading = rng.uniform(0, 2 * np.pi, _MAX_DRAWS)
    translation = speed[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    if model.name == "translation":
        return translation
    if model.name == "affine4":
        return np.column_stack([translation, rng.uniform(-1, 1, (_MAX_DRAWS, 2)) * _MAX_DIVERGENCE * slow])
    return rng.uniform(-1, 1, (_MAX_DRAWS, model.n_params)) * _MAX_ANGULAR * slow


def _check_sensor_size(sensor_size) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in sensor_size)
        exact = all(float(v) == int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise ConfigError(f"sensor_size must be (H, W), got {sensor_size!r}") from None
    if not exact or not (16 <= height <= 32768 and 16 <= width <= 32768):
        raise ConfigError(f"sensor_size (H, W) must be integers from 16 to 32768, got {sensor_size!r}")
    return height, width


def _motion_models(motion_model, object_motion_models, n_objects, sensor_size) -> list[MotionModel]:
    objects = [motion_model] * n_objects if object_motion_models is None else list(object_motion_models)
    names = [motion_model, *objects]
    if len(names) != n_objects + 1:
        raise ConfigError(f"object_motion_models must name {n_objects} models, got {len(names) - 1}")
    for name in names:
        if name not in MOTION_MODELS:
            raise ConfigError(f"unknown motion model {name!r}; choose one of {sorted(MOTION_MODELS)}")
    return [make_motion_model(name, sensor_size) for name in names]


def _layer_params(layer_params, models) -> list[np.ndarray | None]:
    if layer_params is None:
        return [None] * len(models)
    if len(layer_params) != len(models):
        raise ConfigError(
            f"layer_params must hold {len(models)} entries (background first), got {len(layer_params)}"
        )
    checked = []
    for label, (theta, model) in enumerate(zip(layer_params, models, strict=True)):
        if theta is not None:
            theta = np.array(theta, dtype=np.float64)
            if theta.shape != (model.n_params,) or not np.all(np.isfinite(theta)):
                raise ConfigError(
                    f"layer_params[{label}] must be {model.n_params} finite {model.name} parameters, "
                    f"got {theta!r}"
                )
        checked.append(theta)
    return checked


def _positive(value, name: str) -> float:
    value = _number(value, name)
    if not value > 0:
        raise ConfigError(f"{name} must be positive, got {value}")
    return value


def _non_negative(value, name: str) -> float:
    value = _number(value, name)
    if not value >= 0:
        raise ConfigError(f"{name} must be non-negative, got {value}")
    return value


def _number(value, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value}")
    return value


def _count(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ConfigError(f"{name} must be an integer of at least {minimum}, got {value!r}")
    return int(value)


def _polygons(shapes, n_objects: int) -> list[np.ndarray]:
    if len(shapes) != n_objects:
        raise ConfigError(f"object_shapes must hold {n_objects} polygons, got {len(shapes)}")
    polygons = [np.array(shape, dtype=np.float64) for shape in shapes]
    for k, polygon in enumerate(polygons):
        if (
            polygon.ndim != 2
            or polygon.shape[0] < 3
            or polygon.shape[1] != 2
            or not np.isfinite(polygon).all()
        ):
            raise ConfigError(
                f"object_shapes[{k}] must be finite (V, 2) vertices with V >= 3, got {polygon.shape}"
            )
    return polygons


def _fraction_range(value) -> tuple[float, float]:
    low, high = _pair(value, "object_size")
    if not 0 < low <= high < 1:
        raise ConfigError(f"object_size must be fractions 0 < low <= high < 1 of the image, got {value!r}")
    return low, high


def _speed_range(value) -> tuple[float, float]:
    low, high = _pair(value, "speed_range")
    if not 0 <= low <= high:
        raise ConfigError(f"speed_range must be 0 <= low <= high px/s, got {value!r}")
    return low, high


def _pair(value, name: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a pair (low, high), got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return low, high
