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
between the two mean times. :func:`extract_correspondences` chains the three steps for one window; the
steps themselves live in :mod:`~evseg_torch.level_one.images`, :mod:`~evseg_torch.level_one.corners`
and :mod:`~evseg_torch.level_one.lucas_kanade`, and this module is where they are imported from.

With the previous window's models (a stream, :meth:`CascadedSegmenter.stream`), tracking is *guided*
(:func:`guided_tracks`): each corner starts Lucas-Kanade where the best-matching previous motion takes
it, without the pyramid, and only corners that no previous motion explains (a new object, a scene
change) are tracked cold. On consecutive windows this keeps as many tracks as cold tracking, slightly
more of them right, in less time (``benchmarks/bench_level_one.py`` times both).

Tracks stay precise while a sub-window smears a corner over a few pixels: with the defaults and a
30 ms window, up to about 600 px/s; faster motions need a shorter ``sub_window_ms``. The defaults
(:class:`~evseg_torch.config.FeatureConfig`'s: 500 corners, more than 2 px apart, quality 0.001) keep
every corner a DAVIS240 window offers: small objects need every track they have, and a tight
forward-backward check (0.25 px), not the corner score, is what rejects the corners of noise.

torch is used only for kornia's corner response (:mod:`~evseg_torch.level_one.corners`); everything
else is NumPy and OpenCV. Lucas-Kanade takes most of the time (every corner tracked there and back),
and most corners fail the forward-backward check; yet tracking fewer corners (the strongest, the best
few in each cell of a grid, or skipping late corners near a forward track) costs small objects tracks,
and level one then finds fewer of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from evseg_torch.config import FeatureConfig
from evseg_torch.errors import ConfigError, EventFormatError
from evseg_torch.events import EVENT_DTYPE, check_sensor_size
from evseg_torch.level_one.corners import detect_corners, detect_corners_batched
from evseg_torch.level_one.images import event_image, to_uint8
from evseg_torch.level_one.lucas_kanade import Tracks, guided_tracks, track_features
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


def extract_correspondences(
    events: np.ndarray,
    sensor_size: tuple[int, int],
    *,
    sub_window: float = FeatureConfig.sub_window,
    sub_window_ms: float | None = None,
    t_ref: int | None = None,
    max_corners: int = FeatureConfig.max_corners,
    min_distance: int = FeatureConfig.min_distance,
    quality_level: float = FeatureConfig.quality_level,
    sigma: float = FeatureConfig.corner_sigma,
    win_size: tuple[int, int] = (FeatureConfig.lk_win_size, FeatureConfig.lk_win_size),
    max_level: int = FeatureConfig.lk_max_level,
    fb_threshold: float = FeatureConfig.fb_threshold,
    both_images: bool = FeatureConfig.both_images,
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
    corners = detect_corners_batched(
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
