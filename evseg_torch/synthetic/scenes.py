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

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from evseg_torch.errors import ConfigError
from evseg_torch.events import EVENT_DTYPE, to_array
from evseg_torch.motion import MotionModel
from evseg_torch.synthetic.checks import (
    check_layer_params,
    check_non_negative,
    check_object_size,
    check_polygons,
    check_positive,
    check_scene_size,
    check_speed_range,
    scene_motion_models,
)
from evseg_torch.synthetic.draws import draw_motions, grid_around, object_shape
from evseg_torch.synthetic.simulation import (
    Layer,
    background_layer,
    object_layer,
    render,
    simulate,
    simulate_noise,
    threshold_for,
)
from evseg_torch.validation import check_integer

__all__ = ["LayerMotion", "SyntheticScene", "make_scene"]

_REFERENCE_WIDTH = 240.0  # the default speeds are for a sensor this wide; they scale with max(H, W)
_MAX_STEP_PX = 0.5  # largest motion between rendered frames, so that linear interpolation holds
_FULL_SPEED_DURATION = 0.1  # longer scenes slow every motion down, so objects stay in view


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
    _layers: tuple[Layer, ...] = field(repr=False)

    @property
    def n_objects(self) -> int:
        return len(self.motions) - 1

    def log_intensity_at(self, t_s: float) -> np.ndarray:
        """The rendered log-intensity frame at ``t_s`` seconds after the start, float32 :math:`(H, W)`."""
        return render(self._layers, self.depth_order, t_s)[0]

    def label_image_at(self, t_s: float) -> np.ndarray:
        """The visible layer at each pixel at ``t_s`` seconds after the start, int64 :math:`(H, W)`."""
        return render(self._layers, self.depth_order, t_s)[1]

    def masks_at(self, t_s: float) -> np.ndarray:
        """The visible part of each object at ``t_s``, bool :math:`(K, H, W)`; row ``k`` is label ``k+1``."""
        labels = self.label_image_at(t_s)
        return labels[None] == np.arange(1, self.n_objects + 1)[:, None, None]

    def boxes_at(self, t_s: float) -> np.ndarray:
        """Boxes ``[x, y, w, h]`` of each object's visible pixels at ``t_s``, float64 :math:`(K, 4)`.

        As :func:`evseg_torch.evaluation.metrics.box_of_points` of the mask's pixel coordinates: ``x, y`` the
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
    height, width = check_scene_size(sensor_size)
    duration = check_positive(duration, "duration")
    n_objects = check_integer(n_objects, "n_objects")
    models = scene_motion_models(motion_model, object_motion_models, n_objects, (height, width))
    given = check_layer_params(layer_params, models)
    if contrast_threshold is not None and n_events is not None:
        raise ConfigError("give at most one of contrast_threshold and n_events")
    threshold = (
        0.2 if contrast_threshold is None else check_positive(contrast_threshold, "contrast_threshold")
    )
    if n_events is not None:
        n_events = check_integer(n_events, "n_events", at_least=1)
    threshold_jitter = check_non_negative(threshold_jitter, "threshold_jitter")
    noise_rate_hz = check_non_negative(noise_rate_hz, "noise_rate_hz")
    if n_time_steps is not None:
        n_time_steps = check_integer(n_time_steps, "n_time_steps", at_least=1)
    t0_us = check_integer(t0_us, "t0_us")
    area_low, area_high = check_object_size(object_size)
    if object_shapes is not None:
        object_shapes = check_polygons(object_shapes, n_objects)
    object_texture_contrast = check_non_negative(object_texture_contrast, "object_texture_contrast")
    if object_texture_contrast > 1:
        raise ConfigError(f"object_texture_contrast must be in [0, 1], got {object_texture_contrast}")
    background_density = check_positive(background_density, "background_density")
    horizon = duration if ambiguity_window is None else check_positive(ambiguity_window, "ambiguity_window")
    slow = min(1.0, _FULL_SPEED_DURATION / duration)
    scale = max(height, width) / _REFERENCE_WIDTH * slow
    speeds = (100.0 * scale, 600.0 * scale) if speed_range is None else check_speed_range(speed_range)
    if min_relative_speed is not None:
        min_relative_speed = check_non_negative(min_relative_speed, "min_relative_speed")
    min_relative = 150.0 * scale if min_relative_speed is None else min_relative_speed
    rng = np.random.default_rng(rng)

    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1).reshape(-1, 2).astype(float)
    shapes = object_shapes or [
        object_shape(rng, (height, width), area_low, area_high) for _ in range(n_objects)
    ]
    corners = np.array([[0.0, 0.0], [width - 1.0, height - 1.0]])
    regions = [grid_around(corners)] + [grid_around(polygon) for polygon in shapes]
    params = draw_motions(models, given, regions, speeds, min_relative, slow, rng)

    layers = [
        background_layer(models[0], params[0], grid, duration, (height, width), background_density, rng)
    ]
    for model, theta, polygon in zip(models[1:], params[1:], shapes, strict=True):
        # The polygon is where the object is at mid-scene; its t = 0 mask is that warped back.
        start = model.warp(polygon, np.full(len(polygon), duration / 2), theta)
        layers.append(object_layer(model, theta, start, grid, (height, width), object_texture_contrast, rng))
    layers = tuple(layers)
    depth_order = tuple(int(k) + 1 for k in rng.permutation(n_objects))

    if n_time_steps is None:
        fastest = max(float(np.abs(layer.flow).max()) for layer in layers)
        n_time_steps = max(1, math.ceil(fastest * duration / _MAX_STEP_PX))
    times = np.linspace(0.0, duration, n_time_steps + 1)
    if n_events is not None:
        threshold = threshold_for(layers, depth_order, times, n_events, rng)
    signal = simulate(layers, depth_order, times, threshold, threshold_jitter, horizon, rng)
    noise = simulate_noise(noise_rate_hz, duration, (height, width), rng)
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
