"""Level one's input: feature correspondences between two raw event images of one window.

Following Section IV-A of the paper, Shi-Tomasi corners are detected on a raw (not motion-compensated)
event count image early in the window and tracked with pyramidal Lucas-Kanade into a count image late
in the window:

1. :func:`event_image` accumulates the events of the first and of the last sub-window (by default
   each a third of the window) into count images of the sensor's size, which :func:`to_uint8`
   blurs lightly and scales to 8 bits with clipping.
2. :func:`detect_corners` smooths an 8-bit image (``cv2.GaussianBlur``), scores it
   with :func:`kornia.feature.gftt_response` (the structure tensor's smaller eigenvalue) and keeps
   local maxima that are more than ``min_distance`` apart and above a relative quality threshold,
   strongest first, as ``cv2.goodFeaturesToTrack`` does; both images go through kornia in one batch.
3. :func:`track_features` runs ``cv2.calcOpticalFlowPyrLK`` forwards and backwards on both 8-bit
   images and keeps tracks that succeed both ways, come back to within ``fb_threshold``
   pixels of their start and end inside the image.

As in the paper, corners are detected on *both* images: those of the early image are tracked
forwards, those of the late image backwards (skipping late corners that a forward track already
reaches). Small moving objects carry few corners, and the second image about doubles their tracks.

Each image stands for the mean timestamp of its events, so a track's time gap ``dt`` is the distance
between the two mean times. :func:`extract_correspondences` chains the three steps for one window.

With the previous window's models (a stream, :meth:`CascadedSegmenter.stream`), tracking is *guided*
(:func:`guided_tracks`): each corner starts Lucas-Kanade where the best-matching previous motion takes
it, without the pyramid, and only corners that no previous motion explains (a new object, a scene
change) are tracked cold. On consecutive windows this keeps as many tracks as cold tracking, slightly
more of them right, and the features take 60-70 % of their cold time (``benchmarks/bench_level_one.py``).

Tracks stay precise while a sub-window smears a corner over a few pixels: with the defaults and a
30 ms window, up to about 600 px/s; faster motions need a shorter ``sub_window_ms``. The defaults
(500 corners, more than 2 px apart, quality 0.001) keep every corner a DAVIS240 window offers (about
300-500 per image on synthetic scenes): small objects need every track they have, and a tight
forward-backward check (0.25 px), not the corner score, is what rejects the corners of noise. On
synthetic scenes of 40k events in 30 ms with motions up to 600 px/s, about 92 % of the kept tracks
end within 1.5 px of where their layer's true motion takes them.

torch is used only for kornia's corner response; everything else is NumPy and OpenCV. Lucas-Kanade
takes about three quarters of the time (two images of about 450 corners each, every corner tracked
there and back), and only about a third of the corners pass the forward-backward check. Tracking fewer
corners (the strongest, the best few in each cell of a grid, or skipping late corners within 3-4 px of
a forward track) costs small objects tracks, and level one then finds fewer of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import kornia
import numpy as np
import torch
from scipy.spatial import cKDTree

from evseg_torch.errors import ConfigError, EventFormatError, ShapeError
from evseg_torch.events import EVENT_DTYPE, check_sensor_size
from evseg_torch.events.images import event_counts
from evseg_torch.motion import MotionModel

__all__ = [
    "Correspondences",
    "Tracks",
    "detect_corners",
    "event_image",
    "extract_correspondences",
    "guided_tracks",
    "to_uint8",
    "track_features",
]


@dataclass(frozen=True)
class Correspondences:
    """Feature positions at two times of one window, the input of level one's model fitting.

    Attributes:
        src: feature positions in the early event image, ``x`` the column, float64 :math:`(M, 2)`.
        dst: the same features tracked into the late event image, float64 :math:`(M, 2)`.
        dt: seconds from the early to the late image (``t_dst - t_src``), float64 :math:`(M,)`.
        t_src: seconds, relative to the window's reference time, at which ``src`` holds.
        t_dst: seconds, relative to the window's reference time, at which ``dst`` holds.
    """

    src: np.ndarray
    dst: np.ndarray
    dt: np.ndarray
    t_src: float
    t_dst: float

    def __len__(self) -> int:
        return int(self.src.shape[0])


class Tracks(NamedTuple):
    """Result of :func:`track_features`, one row per input point.

    Attributes:
        src: the input points, float64 :math:`(N, 2)`.
        dst: their tracked positions in the second image, float64 :math:`(N, 2)`; only meaningful
            where ``keep`` is True.
        keep: True for tracks that passed every check, bool :math:`(N,)`.
    """

    src: np.ndarray
    dst: np.ndarray
    keep: np.ndarray


def event_image(xy, sensor_size: tuple[int, int]) -> np.ndarray:
    """Count events per pixel, without motion compensation.

    The counts are :func:`~evseg_torch.event_images.event_counts`'s, except that positions outside the
    sensor are refused here rather than dropped: level one's images must hold every event of the window.

    Args:
        xy: event pixel positions, ``x`` the column and ``y`` the row, :math:`(N, 2)`; float positions
            are rounded to the nearest pixel.
        sensor_size: ``(H, W)``.

    Returns:
        float32 image :math:`(H, W)` whose pixels hold event counts.

    Raises:
        ShapeError: ``xy`` is not :math:`(N, 2)`.
        EventFormatError: a position lies outside the sensor or is not finite, or ``sensor_size`` is
            invalid.

    Examples:
        >>> event_image(np.array([[0, 0], [2, 1], [2, 1]]), (2, 3))
        array([[1., 0., 0.],
               [0., 0., 2.]], dtype=float32)
    """
    height, width = check_sensor_size(sensor_size)
    xy = np.asarray(xy)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ShapeError(f"xy must be (N, 2) pixel positions, got shape {xy.shape}")
    if xy.dtype.kind == "f":
        if not np.all(np.isfinite(xy)):
            raise EventFormatError("xy holds NaN or inf")
        xy = np.rint(xy)
    x, y = xy[:, 0].astype(np.int64), xy[:, 1].astype(np.int64)
    outside = (x < 0) | (x >= width) | (y < 0) | (y >= height)
    if np.any(outside):
        first = int(np.argmax(outside))
        raise EventFormatError(
            f"event {first} at (x={x[first]}, y={y[first]}) lies outside the sensor "
            f"(H, W) = {(height, width)}; check sensor_size"
        )
    return event_counts(xy, (height, width)).astype(np.float32)


def detect_corners(
    image,
    *,
    max_corners: int = 500,
    min_distance: int = 2,
    quality_level: float = 0.001,
    sigma: float = 1.0,
) -> np.ndarray:
    """Shi-Tomasi corners of an image, strongest first.

    The image is smoothed with a Gaussian of standard deviation ``sigma`` (event count images are
    spiky; ``sigma=0`` skips it), scored with :func:`kornia.feature.gftt_response` (which itself
    integrates the structure tensor over a fixed 7x7, σ=1 window), and a pixel is kept when its
    score is the maximum of the :math:`(2 d + 1) \\times (2 d + 1)` square around it, ``d`` being
    ``min_distance``, and exceeds ``quality_level`` times the image's best score. A negligible
    position-dependent ramp breaks ties between equal scores, so every two kept corners are more
    than ``min_distance`` apart along ``x`` or ``y``, hence also in Euclidean distance. This
    suppression is stricter than OpenCV's greedy one: a corner also hides weaker maxima of its
    square that a greedy pass would keep after their suppressor had been suppressed itself.

    Args:
        image: :math:`(H, W)` array, e.g. from :func:`event_image`.
        max_corners: keep at most this many corners, the strongest.
        min_distance: minimum distance in pixels between corners, at least 1.
        quality_level: relative score threshold in ``[0, 1)``, as in ``cv2.goodFeaturesToTrack``.
        sigma: standard deviation in pixels of the pre-smoothing, ``>= 0``.

    Returns:
        float64 :math:`(M, 2)` corner positions ``(x, y)`` on the pixel grid, ``M <= max_corners``,
        in decreasing order of score; :math:`(0, 2)` for an image without structure.

    Raises:
        ShapeError: ``image`` is not 2-D.
        ConfigError: a parameter is out of range.
    """
    image = _check_image(image, "image")
    return _detect_corners(image[None], max_corners, min_distance, quality_level, sigma)[0]


def _detect_corners(
    images: np.ndarray, max_corners: int, min_distance: int, quality_level: float, sigma: float
) -> list[np.ndarray]:
    """:func:`detect_corners` of a stack of images :math:`(B, H, W)`, scored in one batched kornia call."""
    if int(max_corners) < 1:
        raise ConfigError(f"max_corners must be at least 1, got {max_corners}")
    if int(min_distance) < 1:
        raise ConfigError(f"min_distance must be at least 1 pixel, got {min_distance}")
    if not 0.0 <= quality_level < 1.0:
        raise ConfigError(f"quality_level must lie in [0, 1), got {quality_level}")
    if not sigma >= 0.0:
        raise ConfigError(f"sigma must be non-negative, got {sigma}")
    _, height, width = images.shape
    images = np.asarray(images, dtype=np.float32)
    if sigma > 0.0:
        # The same kernel and reflecting border as kornia.filters.gaussian_blur2d, at a fraction of its cost.
        size = 2 * math.ceil(3.0 * sigma) + 1
        images = np.stack(
            [
                cv2.GaussianBlur(image, (size, size), sigma, borderType=cv2.BORDER_REFLECT_101)
                for image in images
            ]
        )
    # oneDNN's convolutions cost several times PyTorch's own on single-channel images this small.
    with (
        torch.inference_mode(),
        torch.backends.mkldnn.flags(enabled=False, deterministic=None, allow_tf32=None, fp32_precision=None),
    ):
        tensor = torch.from_numpy(np.ascontiguousarray(images))[:, None]
        scores = kornia.feature.gftt_response(tensor)[:, 0].numpy().astype(np.float64)
    # The ramp adds at most 1e-9 of the best score: below float32 resolution of every score above 2 %
    # of the best, so it orders ties and nothing else, while its steps stay resolvable in float64.
    ramp = np.arange(height * width, 0, -1, dtype=np.float64).reshape(height, width)
    ramp *= 1e-9 / (height * width)
    side = 2 * int(min_distance) + 1
    corners = []
    for score in scores:
        best = float(score.max())
        if not best > 0.0:
            corners.append(np.zeros((0, 2), dtype=np.float64))
            continue
        score += ramp * best
        # A grey dilation is the separable running maximum: the max-pool NMS at a fraction of its cost.
        peaks = score == cv2.dilate(score, np.ones((side, side), np.uint8))
        peaks &= score > best * max(quality_level, 1e-6)
        rows, cols = np.nonzero(peaks)
        order = np.argsort(-score[rows, cols], kind="stable")[: int(max_corners)]
        corners.append(np.column_stack([cols[order], rows[order]]).astype(np.float64))
    return corners


def to_uint8(image, *, sigma: float = 1.0, percentile: float = 99.5) -> np.ndarray:
    """Smooth a count image and scale it to ``uint8`` for OpenCV's Lucas-Kanade.

    A light Gaussian blur (``cv2.GaussianBlur``) turns the sparse, spiky counts into the smooth
    intensities LK's gradients need; on synthetic scenes, σ = 1 px gives the most precise tracks
    (σ = 0.7 about 2 % fewer within 1.5 px of the truth, σ = 1.5 a sixth fewer tracks). Counts are
    then multiplied by ``255 / c``, where ``c`` is the ``percentile`` of the *non-zero* pixels (most
    pixels of an event image are empty, so a percentile over all of them would often be 0), rounded
    and clipped. Normalising each image by its own scale keeps LK's brightness constancy when the
    two sub-windows hold different numbers of events, and the clipping keeps hot pixels and bursts
    from darkening everything else.

    Args:
        image: non-negative :math:`(H, W)` array.
        sigma: standard deviation of the blur in pixels, ``>= 0`` (0: none).
        percentile: the percentile of non-zero pixels that maps to 255, in ``(0, 100]``.

    Returns:
        uint8 :math:`(H, W)`.
    """
    image = np.asarray(_check_image(image, "image"), dtype=np.float32)
    if not sigma >= 0.0 or not 0.0 < percentile <= 100.0:
        raise ConfigError(f"need sigma >= 0 and 0 < percentile <= 100, got {sigma} and {percentile}")
    if sigma > 0.0:
        image = cv2.GaussianBlur(image, (0, 0), sigma)
    nonzero = image[image > 0]
    scale = float(np.percentile(nonzero, percentile)) if nonzero.size else 1.0
    # Rounds half to even and saturates, as np.clip(np.rint(...)) would, several times faster.
    return cv2.convertScaleAbs(image, alpha=255.0 / scale)


def track_features(
    image0,
    image1,
    points,
    *,
    win_size: tuple[int, int] = (21, 21),
    max_level: int = 3,
    fb_threshold: float = 0.25,
    max_iterations: int = 30,
    epsilon: float = 0.01,
    initial=None,
) -> Tracks:
    """Track points from one image into another with pyramidal Lucas-Kanade.

    Images that are not ``uint8`` are converted with :func:`to_uint8`. Points are tracked forwards
    with ``cv2.calcOpticalFlowPyrLK`` and those that succeed (OpenCV's status) inside the image are
    tracked backwards; a track is kept when that pass succeeds too and returns to within
    ``fb_threshold`` pixels of the start.

    With ``initial`` guesses of where the points are in ``image1``, LK starts there instead of at the
    points themselves (``cv2.OPTFLOW_USE_INITIAL_FLOW``), and the backward pass starts from each track's
    end moved back by its guessed displacement. A guess within a few pixels needs no pyramid
    (``max_level=0``), several times cheaper than a pyramidal search.

    Args:
        image0: first image :math:`(H, W)`.
        image1: second image :math:`(H, W)`.
        points: positions ``(x, y)`` in ``image0``, :math:`(N, 2)`.
        win_size: LK search window ``(width, height)`` at each pyramid level.
        max_level: number of pyramid levels above the full image (0: no pyramid).
        fb_threshold: largest forward-backward round-trip error in pixels, positive.
        max_iterations: LK iterations per level.
        epsilon: LK stops when an update is smaller than this many pixels.
        initial: guessed positions in ``image1``, :math:`(N, 2)`, or ``None``.

    Returns:
        :class:`Tracks` ``(src, dst, keep)`` with one row per point.

    Raises:
        ShapeError: images of different or non-2-D shapes, or ``points`` not :math:`(N, 2)`.
        ConfigError: a parameter is out of range.
    """
    frames = _frame_pair(image0, image1)
    src = np.array(points, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 2:
        raise ShapeError(f"points must be (N, 2), got shape {src.shape}")
    if not fb_threshold > 0.0:
        raise ConfigError(f"fb_threshold must be positive, got {fb_threshold}")
    if int(max_level) < 0 or int(max_iterations) < 1 or not epsilon > 0.0:
        raise ConfigError(
            "need max_level >= 0, max_iterations >= 1 and epsilon > 0, "
            f"got {max_level}, {max_iterations} and {epsilon}"
        )
    guess = None
    if initial is not None:
        guess = np.asarray(initial, dtype=np.float64)
        if guess.shape != src.shape or not np.all(np.isfinite(guess)):
            raise ShapeError(f"initial must be finite guesses of shape {src.shape}, got shape {guess.shape}")
    if src.shape[0] == 0:
        return Tracks(src, src.copy(), np.zeros(0, dtype=bool))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iterations), float(epsilon))
    lk = {"winSize": tuple(int(v) for v in win_size), "criteria": criteria, "maxLevel": int(max_level)}
    if guess is not None:
        lk["flags"] = cv2.OPTFLOW_USE_INITIAL_FLOW
    start = src.astype(np.float32).reshape(-1, 1, 2)
    forward, status, _ = cv2.calcOpticalFlowPyrLK(frames[0], frames[1], start, _lk_guess(guess, start), **lk)
    dst = forward.reshape(-1, 2).astype(np.float64)
    height, width = frames[0].shape
    inside = (dst[:, 0] >= 0) & (dst[:, 0] <= width - 1) & (dst[:, 1] >= 0) & (dst[:, 1] <= height - 1)
    keep = (status.ravel() == 1) & inside & np.all(np.isfinite(dst), axis=1)
    # Only the forward results that can still be kept are tracked back: the same tracks, and a few
    # percent fewer points for the backward pass.
    checked = np.flatnonzero(keep)
    if checked.size:
        back_guess = None if guess is None else dst[checked] - (guess[checked] - src[checked])
        backward, status, _ = cv2.calcOpticalFlowPyrLK(
            frames[1], frames[0], forward[checked], _lk_guess(back_guess, forward[checked]), **lk
        )
        round_trip = np.linalg.norm(backward.reshape(-1, 2).astype(np.float64) - src[checked], axis=1)
        keep[checked] = (status.ravel() == 1) & (round_trip <= fb_threshold)
    return Tracks(src, dst, keep)


def extract_correspondences(
    events: np.ndarray,
    sensor_size: tuple[int, int],
    *,
    sub_window: float = 1.0 / 3.0,
    sub_window_ms: float | None = None,
    t_ref: int | None = None,
    max_corners: int = 500,
    min_distance: int = 2,
    quality_level: float = 0.001,
    sigma: float = 1.0,
    win_size: tuple[int, int] = (21, 21),
    max_level: int = 3,
    fb_threshold: float = 0.25,
    both_images: bool = True,
    motion: MotionModel | None = None,
    initial_models=None,
) -> Correspondences:
    """Feature correspondences between the beginning and the end of one window of events.

    The window spans the first to the last event. The early image accumulates the events of its
    first ``sub_window`` fraction, the late image those of its last; each image stands for the mean
    timestamp of its events (at a constant event rate, its sub-window's middle, so that every track
    spans ``dt = (1 - sub_window) * duration``). A third (the default) balances two needs: enough
    events per image for stable corners, and a gap long enough for displacements of a few pixels
    while each image's own motion blur stays below a third of the window's motion (on EED, shorter
    or longer sub-windows found fewer balls).
    Tracks from the early image's corners come first in the result, then those of the late image.

    Args:
        events: canonical events of one window (:data:`evseg_torch.events.EVENT_DTYPE`), sorted.
        sensor_size: ``(H, W)``.
        sub_window: length of each sub-window as a fraction of the window, in ``(0, 0.5]``.
        sub_window_ms: length of each sub-window in milliseconds; when given it replaces
            ``sub_window`` and is capped at half the window.
        t_ref: reference time in microseconds for ``t_src`` and ``t_dst``; defaults to the first
            event's timestamp.
        max_corners, min_distance, quality_level, sigma: see :func:`detect_corners`; ``max_corners``
            applies to each image.
        win_size, max_level, fb_threshold: see :func:`track_features`.
        both_images: also detect corners on the late image and track them backwards (the paper's
            scheme); ``False`` tracks the early image's corners only.
        motion: the motion family of ``initial_models``.
        initial_models: a previous window's models :math:`(K, P)` of ``motion``, to guide the tracking
            (see :func:`guided_tracks`); ``None`` or none at all tracks every corner cold.

    Returns:
        :class:`Correspondences` of the kept tracks (possibly none), at most ``2 * max_corners``.

    Raises:
        EventFormatError: events not canonical, empty, outside ``sensor_size`` or all at one time.
        ConfigError: a parameter is out of range, or ``initial_models`` come without ``motion``.
        ModelError: ``initial_models`` do not fit ``motion``.
    """
    height, width = check_sensor_size(sensor_size)
    guides = None
    if initial_models is not None:
        if motion is None:
            raise ConfigError("initial_models need the motion model they belong to (motion=...)")
        guides = motion.check_instances(initial_models)
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE:
        raise EventFormatError(
            f"events must be canonical (dtype {EVENT_DTYPE}); convert them with evseg_torch.events.as_events"
        )
    if events.ndim != 1 or events.shape[0] == 0:
        raise EventFormatError(f"need a non-empty 1-D array of events, got shape {events.shape}")
    t_us = events["t"]
    t_first, t_last = int(t_us[0]), int(t_us[-1])
    duration = t_last - t_first
    if duration <= 0:
        raise EventFormatError(
            f"the window spans {duration} us; correspondences need events at two different times"
        )
    if sub_window_ms is not None:
        if not sub_window_ms > 0.0:
            raise ConfigError(f"sub_window_ms must be positive, got {sub_window_ms}")
        length = min(float(sub_window_ms) * 1e3, 0.5 * duration)
    elif 0.0 < sub_window <= 0.5:
        length = float(sub_window) * duration
    else:
        raise ConfigError(f"sub_window must be a fraction in (0, 0.5], got {sub_window}")
    # Sub-window bounds are inclusive on the outside and exclusive inside, rounded so that the
    # early image always holds the first event and the late one the last.
    early_end = np.searchsorted(t_us, t_first + length, side="left")
    late_begin = np.searchsorted(t_us, t_last - length, side="right")
    early = slice(0, max(int(early_end), 1))
    late = slice(min(int(late_begin), len(events) - 1), None)
    xy = np.column_stack([events["x"], events["y"]])
    # Corners are detected on the 8-bit image that LK tracks: its clipping keeps hot pixels and bursts
    # from raising the relative quality threshold above every genuine corner.
    image0 = to_uint8(event_image(xy[early], (height, width)))
    image1 = to_uint8(event_image(xy[late], (height, width)))
    # Each image stands for the mean time of its events rather than its sub-window's middle: the event
    # rate is not flat (a scene's first milliseconds, bursts), and an image's edges lie where they
    # were at its events' mean time.
    origin = t_first if t_ref is None else int(t_ref)
    t_src = (float(np.mean(t_us[early])) - origin) * 1e-6
    t_dst = (float(np.mean(t_us[late])) - origin) * 1e-6
    corners = _detect_corners(
        np.stack([image0, image1]) if both_images else image0[None],
        max_corners,
        min_distance,
        quality_level,
        sigma,
    )
    track = {"win_size": win_size, "max_level": max_level, "fb_threshold": fb_threshold}

    def follow(start, end, points, gap):
        if guides is None or len(guides) == 0:
            return track_features(start, end, points, **track)
        return guided_tracks(start, end, points, motion.predict(points, gap, guides), **track)

    forward = follow(image0, image1, corners[0], t_dst - t_src)
    src, dst = forward.src[forward.keep], forward.dst[forward.keep]
    if both_images:
        # Corners of the late image give the tracks of texture that only shows up there and add tracks
        # on small objects; those within min_distance of a forward track's end would duplicate it.
        late_corners = corners[1]
        if len(dst) and len(late_corners):
            gaps = cKDTree(dst).query(late_corners, distance_upper_bound=min_distance)[0]
            late_corners = late_corners[gaps > min_distance]
        backward = follow(image1, image0, late_corners, t_src - t_dst)
        src = np.concatenate([src, backward.dst[backward.keep]])
        dst = np.concatenate([dst, backward.src[backward.keep]])
    return Correspondences(
        src=src, dst=dst, dt=np.full(len(src), t_dst - t_src, dtype=np.float64), t_src=t_src, t_dst=t_dst
    )


# A guide that holds for fewer points than this is wrong as a whole. Guided passes keep 15-65 % of the
# corners of synthetic scenes, about as many as cold passes do.
_MIN_GUIDED_FRACTION = 0.05


def guided_tracks(
    image0,
    image1,
    points,
    candidates,
    *,
    rescue_ratio: float = 2.0,
    patch_radius: int = 3,
    guided_iterations: int = 6,
    **track,
) -> Tracks:
    """Track points whose motion is probably one of a few known ones, e.g. the previous window's.

    Each point starts Lucas-Kanade from the candidate position whose patch of ``image1`` looks most
    like the point's patch of ``image0`` (mean absolute difference of :math:`(2r+1)^2` pixels, ``r``
    being ``patch_radius``), on the full image only: a guess within a few pixels needs no pyramid.
    Points that this fails for *and* that no candidate explains (their best patch difference exceeds
    ``rescue_ratio`` times the median of the kept tracks') belong to a motion the candidates lack,
    e.g. a newly appearing object, and are tracked cold with the pyramid. Points that a candidate
    explains but that fail the forward-backward check are mostly the image's noise, which a cold pass
    drops as well. But when the guided pass keeps hardly any point (under 5 %), or the rescued points
    keep tracks more often than the guided ones, the candidates miss the image's main motions (a
    scene change) and every point the guided pass failed for is tracked cold.

    Args:
        image0: first image :math:`(H, W)`.
        image1: second image :math:`(H, W)`.
        points: positions ``(x, y)`` in ``image0``, :math:`(N, 2)`.
        candidates: where each known motion takes each point, :math:`(K, N, 2)`; a guess outside the
            image or not finite fails, and its point is tracked cold.
        rescue_ratio: patch difference, relative to that of the kept tracks, above which a failed
            point is tracked cold.
        patch_radius: half-side in pixels of the compared patches.
        guided_iterations: Lucas-Kanade iterations of the guided pass. From a guess a few pixels off,
            a handful converge; more only let the tracks of noise wander off and pass the check (on
            synthetic scenes 6 iterations keep 94 % of the tracks within 1.5 px of the truth, 30 keep
            92 %).
        **track: :func:`track_features`' keyword arguments for the cold pass; the guided pass uses
            the same ones without the pyramid.

    Returns:
        :class:`Tracks` ``(src, dst, keep)`` with one row per point.

    Raises:
        ShapeError: ``candidates`` is not :math:`(K, N, 2)` with ``K >= 1``.
    """
    image0, image1 = _frame_pair(image0, image1)
    src = np.array(points, dtype=np.float64)
    candidates = np.asarray(candidates, dtype=np.float64)
    if candidates.ndim != 3 or candidates.shape[0] < 1 or candidates.shape[1:] != src.shape:
        raise ShapeError(f"candidates must be (K, N, 2) for {src.shape[0]} points, got {candidates.shape}")
    if src.shape[0] == 0:
        return track_features(image0, image1, src, **track)
    # Wild or non-finite guesses (a diverged model) fail at the border like any other bad guess.
    height, width = image0.shape
    candidates = np.clip(np.where(np.isnan(candidates), -1.0, candidates), -1.0, [width, height])
    costs = _patch_differences(image0, image1, src, candidates, int(patch_radius))
    best = np.argmin(costs, axis=0)
    cost = costs[best, np.arange(len(src))]
    guess = candidates[best, np.arange(len(src))]
    guided = track_features(
        image0,
        image1,
        src,
        **{**track, "max_level": 0, "max_iterations": guided_iterations, "initial": guess},
    )
    failed = ~guided.keep
    rescue = failed.copy()
    if guided.keep.mean() >= _MIN_GUIDED_FRACTION:
        rescue &= cost > rescue_ratio * float(np.median(cost[guided.keep]))
    dst, keep = guided.dst.copy(), guided.keep.copy()
    for cold_points in (rescue, failed & ~rescue):
        if not cold_points.any():
            break
        cold = track_features(image0, image1, src[cold_points], **track)
        dst[cold_points], keep[cold_points] = cold.dst, cold.keep
        # Rescued points that track more often than guided ones: the candidates miss the image's
        # main motions (a scene change), and every point they failed for is tracked cold.
        if cold.keep.mean() <= guided.keep.mean():
            break
    return Tracks(src, dst, keep)


def _patch_differences(image0, image1, points, candidates, radius: int) -> np.ndarray:
    """Mean absolute difference of the nearest-pixel patches at ``points`` in ``image0`` and at each
    candidate in ``image1``, :math:`(K, N)`; patches are clipped at the image border."""
    height, width = image0.shape
    offsets = np.arange(-radius, radius + 1)

    def patches(image, xy):
        cols = np.clip(np.rint(xy[..., 0]).astype(np.int64)[..., None, None] + offsets, 0, width - 1)
        rows = np.clip(
            np.rint(xy[..., 1]).astype(np.int64)[..., None, None] + offsets[:, None], 0, height - 1
        )
        return image[rows, cols].astype(np.int16)

    return np.abs(patches(image1, candidates) - patches(image0, points)).mean(axis=(-2, -1))


def _lk_guess(guess: np.ndarray | None, start: np.ndarray) -> np.ndarray | None:
    """OpenCV's ``nextPts`` argument: the guesses as float32 :math:`(N, 1, 2)`, or ``None``."""
    return None if guess is None else guess.astype(np.float32).reshape(start.shape)


def _frame_pair(image0, image1) -> tuple[np.ndarray, np.ndarray]:
    """Two 2-D images of one shape as Lucas-Kanade's ``uint8`` frames (:func:`to_uint8` where needed)."""
    image0 = _check_image(image0, "image0")
    image1 = _check_image(image1, "image1")
    if image0.shape != image1.shape:
        raise ShapeError(f"image0 and image1 must have the same shape, got {image0.shape} and {image1.shape}")
    return tuple(image if image.dtype == np.uint8 else to_uint8(image) for image in (image0, image1))


def _check_image(image, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise ShapeError(f"{name} must be a 2-D (H, W) image, got shape {image.shape}")
    return image
