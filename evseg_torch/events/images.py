"""Images of events in NumPy: how many events fall on each pixel, in total or per label.

This is the one place where events are counted on the pixel grid (nearest pixel, not differentiable);
level one's raw event images, the figures and the evaluation protocols' compensated count images are
all built on :func:`event_counts`. The differentiable, bilinear image of warped events used by level two
is :func:`evseg_torch.level_two.image.splat.splat_events`, a different thing.
"""

from __future__ import annotations

import numpy as np

from evseg_torch.errors import ShapeError
from evseg_torch.events.format import check_sensor_size


def event_counts(xy, sensor_size: tuple[int, int], labels=None, n_labels: int | None = None) -> np.ndarray:
    """Count the events on each pixel, optionally one image per label.

    Float positions are rounded to the nearest pixel (``np.rint``, halves to even). Events whose
    rounded position lies outside the sensor, or is not finite, are dropped silently: callers that must
    refuse them (e.g. :func:`evseg_torch.level_one.event_image`) validate the positions first.

    Args:
        xy: event positions, ``x`` the column and ``y`` the row, :math:`(N, 2)`, integer or float.
        sensor_size: ``(H, W)``.
        labels: optional integer label of each event, :math:`(N,)`; each label ``k`` gets its own image.
            Events whose label is outside ``[0, K)`` (e.g. ``-1``, unassigned) are dropped.
        n_labels: ``K``, the number of label images; defaults to ``labels.max() + 1`` (0 for no events).
            Only with ``labels``.

    Returns:
        int64 counts, :math:`(H, W)` without ``labels``, :math:`(K, H, W)` with them (image ``k`` counts
        the events labelled ``k``).

    Raises:
        ShapeError: ``xy`` is not :math:`(N, 2)`, or ``labels`` is not :math:`(N,)` integers.
        EventFormatError: ``sensor_size`` is invalid.

    Examples:
        >>> xy = np.array([[0.2, 0.4], [2.0, 1.0], [1.6, 0.9], [5.0, 0.0]])
        >>> event_counts(xy, (2, 3))
        array([[1, 0, 0],
               [0, 0, 2]])
        >>> event_counts(xy, (2, 3), labels=np.array([1, 1, -1, 0]), n_labels=2)
        array([[[0, 0, 0],
                [0, 0, 0]],
        <BLANKLINE>
               [[1, 0, 0],
                [0, 0, 1]]])
    """
    height, width = check_sensor_size(sensor_size)
    xy = np.asarray(xy)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ShapeError(f"xy must be (N, 2) pixel positions, got shape {xy.shape}")
    if xy.dtype.kind == "f":
        xy = np.rint(xy)
    x, y = xy[:, 0], xy[:, 1]
    # Compared before the cast to int64: NaN and inf fail every comparison, and huge floats would wrap.
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    index = y[inside].astype(np.int64) * width + x[inside].astype(np.int64)
    n_images = 1
    if labels is not None:
        labels = np.asarray(labels)
        if labels.shape != (len(xy),) or labels.dtype.kind not in "iub":
            raise ShapeError(
                f"labels must be (N,) integers with xy (N, 2), got {labels.dtype} {labels.shape}"
            )
        labels = labels.astype(np.int64, copy=False)
        n_images = int(labels.max(initial=-1)) + 1 if n_labels is None else int(n_labels)
        owner = labels[inside]
        valid = (owner >= 0) & (owner < n_images)
        index = owner[valid] * (height * width) + index[valid]
    counts = np.bincount(index, minlength=n_images * height * width).reshape(n_images, height, width)
    return counts if labels is not None else counts[0]
