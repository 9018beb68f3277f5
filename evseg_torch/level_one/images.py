"""Level one's event images: raw event counts of a sub-window, and their 8-bit form for OpenCV.

:func:`event_image` counts a sub-window's events per pixel, without motion compensation;
:func:`to_uint8` blurs such a count image lightly and scales it to 8 bits with clipping, the image on
which corners are detected (:mod:`~evseg_torch.level_one.corners`) and Lucas-Kanade tracks them
(:mod:`~evseg_torch.level_one.lucas_kanade`). NumPy and OpenCV only.
"""

from __future__ import annotations

import cv2
import numpy as np

from evseg_torch.errors import ConfigError, EventFormatError, ShapeError
from evseg_torch.events import check_sensor_size
from evseg_torch.events.images import event_counts

__all__ = ["check_image", "event_image", "to_uint8"]


def event_image(xy, sensor_size: tuple[int, int]) -> np.ndarray:
    """Count events per pixel, without motion compensation.

    The counts are :func:`~evseg_torch.events.images.event_counts`'s, except that positions outside the
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


def to_uint8(image, *, sigma: float = 1.0, percentile: float = 99.5) -> np.ndarray:
    """Smooth a count image and scale it to ``uint8`` for OpenCV's Lucas-Kanade.

    A light Gaussian blur (``cv2.GaussianBlur``) turns the sparse, spiky counts into the smooth
    intensities LK's gradients need; on synthetic scenes, σ = 1 px gives the most precise tracks
    (a narrower blur leaves fewer of them right, a wider one fewer of them). Counts are
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
    image = np.asarray(check_image(image, "image"), dtype=np.float32)
    if not sigma >= 0.0 or not 0.0 < percentile <= 100.0:
        raise ConfigError(f"need sigma >= 0 and 0 < percentile <= 100, got {sigma} and {percentile}")
    if sigma > 0.0:
        image = cv2.GaussianBlur(image, (0, 0), sigma)
    nonzero = image[image > 0]
    scale = float(np.percentile(nonzero, percentile)) if nonzero.size else 1.0
    # Rounds half to even and saturates, as np.clip(np.rint(...)) would, several times faster.
    return cv2.convertScaleAbs(image, alpha=255.0 / scale)


def check_image(image, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise ShapeError(f"{name} must be a 2-D (H, W) image, got shape {image.shape}")
    return image
