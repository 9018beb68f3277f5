"""Shi-Tomasi corners of level one's event images, scored by kornia (the one use of torch in level one).

:func:`detect_corners` smooths an image, scores it with :func:`kornia.feature.gftt_response` and keeps
the strongest local maxima, as ``cv2.goodFeaturesToTrack`` does; :func:`detect_corners_batched` does
the same for a stack of images in one kornia call (a window's early and late images).
"""

from __future__ import annotations

import math

import cv2
import kornia
import numpy as np
import torch

from evseg_torch.config import FeatureConfig
from evseg_torch.errors import ConfigError
from evseg_torch.level_one.images import check_image
from evseg_torch.validation import check_integer

__all__ = ["detect_corners", "detect_corners_batched"]


def detect_corners(
    image,
    *,
    max_corners: int = FeatureConfig.max_corners,
    min_distance: int = FeatureConfig.min_distance,
    quality_level: float = FeatureConfig.quality_level,
    sigma: float = FeatureConfig.corner_sigma,
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
    image = check_image(image, "image")
    return detect_corners_batched(image[None], max_corners, min_distance, quality_level, sigma)[0]


def detect_corners_batched(
    images: np.ndarray, max_corners: int, min_distance: int, quality_level: float, sigma: float
) -> list[np.ndarray]:
    """:func:`detect_corners` of a stack of images :math:`(B, H, W)`, scored in one batched kornia call."""
    max_corners = check_integer(max_corners, "max_corners", at_least=1)
    min_distance = check_integer(min_distance, "min_distance", at_least=1)
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
    side = 2 * min_distance + 1
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
        order = np.argsort(-score[rows, cols], kind="stable")[:max_corners]
        corners.append(np.column_stack([cols[order], rows[order]]).astype(np.float64))
    return corners
