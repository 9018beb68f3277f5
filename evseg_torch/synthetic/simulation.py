"""The simulation of a scene's events: layers rendered to log-intensity frames, ESIM between frames.

Each layer (:class:`Layer`) is a texture with its coverage at ``t = 0`` and its motion on the pixel grid;
:func:`render` composites the layers back to front at a time, and :func:`simulate` emits one event per
contrast-threshold crossing of each pixel between consecutive frames, with its label and ambiguity flag
(the rules are in :mod:`evseg_torch.synthetic.scenes`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np

# An object covers a pixel where its anti-aliased coverage exceeds this: then the events of its moving
# silhouette, trailing edge included, are its own, as its motion explains them.
_COVERED = 0.05
_MASK_SHIFT = 4  # sub-pixel bits of polygon vertices (cv2.fillPoly's shift)
_COUNT_PIXELS = 3000  # pixels simulated to choose the contrast threshold for a requested event count
_THRESHOLD_SEARCH = (0.01, 2.0)  # range of contrast thresholds searched for a requested event count


@dataclass(frozen=True, eq=False)
class Layer:
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


def render(layers: tuple[Layer, ...], depth_order: tuple[int, ...], t: float) -> tuple[np.ndarray, ...]:
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


def threshold_for(layers, depth_order, times, n_events: int, rng) -> float:
    """The contrast threshold that yields about ``n_events`` events.

    Counts the events of a grid of candidate thresholds at once on a sparse subset of the pixels
    (a few thousand, rendered alone, so this costs a fraction of the simulation), then interpolates
    the count, which falls monotonically with the threshold, in log-log scale.
    """
    height, width = layers[0].flow.shape[1:]
    stride = max(1, math.isqrt(height * width // _COUNT_PIXELS))
    every = (slice(None), slice(stride // 2, None, stride), slice(stride // 2, None, stride))
    sparse = tuple(Layer(layer.image, layer.base[every], layer.flow[every]) for layer in layers)
    candidates = np.geomspace(*_THRESHOLD_SEARCH, 16)[:, None]
    previous = render(sparse, depth_order, times[0])[0].ravel()
    reference = previous + candidates * rng.uniform(-1.0, 1.0, previous.shape)
    counts = np.zeros(len(candidates))
    for t in times[1:]:
        change = render(sparse, depth_order, t)[0].ravel() - reference
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


def simulate(layers, depth_order, times, threshold, jitter, horizon, rng):
    """ESIM between consecutive frames: one event per threshold crossing, time linearly interpolated.

    Returns times, pixels ``(x, y)``, polarities, labels and the ambiguity flags of the events. An event
    is ambiguous when, within ``horizon`` seconds before it, its pixel was dominated by a layer in
    front of the one dominating it at the end of its interval: uncovered behind an object, from the
    trailing edge's second half on (the leading edge never is).
    """
    previous, previous_labels, dominant = (a.ravel() for a in render(layers, depth_order, times[0]))
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
        frame, frame_labels, dominant = (a.ravel() for a in render(layers, depth_order, t_end))
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


def simulate_noise(rate_hz, duration, sensor_size, rng):
    """Noise events uniform in space and time: times, pixels, polarities, labels (-1) and ambiguity."""
    height, width = sensor_size
    count = rng.poisson(rate_hz * height * width * duration)
    xy = np.column_stack([rng.integers(0, width, count), rng.integers(0, height, count)])
    t_s, polarity = rng.uniform(0.0, duration, count), rng.choice(np.array([-1, 1]), count)
    return t_s, xy, polarity, np.full(count, -1), np.zeros(count, dtype=bool)


def background_layer(model, theta, grid, duration, sensor_size, density, rng) -> Layer:
    """A textured log-intensity image covering every point the sensor sees over the scene."""
    flow = model.velocity(grid, theta)
    # warp is linear in t, so the sensor's pixels sweep the texture between t = 0 and t = duration.
    seen = np.concatenate([grid, grid - duration * flow])
    low = np.floor(seen.min(axis=0)) - 3
    size = (np.ceil(seen.max(axis=0)) + 4 - low).astype(int)
    texture = _background_texture(rng, (int(size[1]), int(size[0])), density)
    return _make_layer(texture, low, grid, flow, sensor_size)


def object_layer(model, theta, polygon, grid, sensor_size, contrast, rng) -> Layer:
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


def _make_layer(image, origin, grid, flow, sensor_size) -> Layer:
    height, width = sensor_size
    base = (grid - origin).T.reshape(2, height, width).astype(np.float32)
    return Layer(image=image, base=base, flow=flow.T.reshape(2, height, width).astype(np.float32))


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
