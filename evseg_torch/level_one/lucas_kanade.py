"""Lucas-Kanade tracks between level one's two event images, cold or guided by known motions.

:func:`track_features` runs OpenCV's pyramidal Lucas-Kanade forwards and backwards and keeps the tracks
that come back to their start; :func:`guided_tracks` starts each point where the best-matching known
motion (a previous window's model) takes it, without the pyramid, and tracks cold only the points
that no known motion explains. NumPy and OpenCV only.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from evseg_torch.config import FeatureConfig
from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.level_one.images import check_image, to_uint8
from evseg_torch.validation import check_integer

__all__ = ["Tracks", "guided_tracks", "track_features"]


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


def track_features(
    image0,
    image1,
    points,
    *,
    win_size: tuple[int, int] = (FeatureConfig.lk_win_size, FeatureConfig.lk_win_size),
    max_level: int = FeatureConfig.lk_max_level,
    fb_threshold: float = FeatureConfig.fb_threshold,
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
    max_level = check_integer(max_level, "max_level")
    max_iterations = check_integer(max_iterations, "max_iterations", at_least=1)
    if not epsilon > 0.0:
        raise ConfigError(f"epsilon must be positive, got {epsilon}")
    guess = None
    if initial is not None:
        guess = np.asarray(initial, dtype=np.float64)
        if guess.shape != src.shape or not np.all(np.isfinite(guess)):
            raise ShapeError(f"initial must be finite guesses of shape {src.shape}, got shape {guess.shape}")
    if src.shape[0] == 0:
        return Tracks(src, src.copy(), np.zeros(0, dtype=bool))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, max_iterations, float(epsilon))
    lk = {"winSize": tuple(int(v) for v in win_size), "criteria": criteria, "maxLevel": max_level}
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


# A guide that holds for fewer points than this is wrong as a whole: a guided pass that follows the
# image's motions keeps about as many corners as a cold pass, far more than this.
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
            a handful converge; more only let the tracks of noise wander off and pass the check.
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
    image0 = check_image(image0, "image0")
    image1 = check_image(image1, "image1")
    if image0.shape != image1.shape:
        raise ShapeError(f"image0 and image1 must have the same shape, got {image0.shape} and {image1.shape}")
    return tuple(image if image.dtype == np.uint8 else to_uint8(image) for image in (image0, image1))
