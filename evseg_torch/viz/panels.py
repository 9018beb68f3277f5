"""The paper's Fig. 1 panels of one window as one RGB image, drawn with NumPy and OpenCV.

One renderer serves the demo figure, the per-window PNGs of ``evseg segment --save-images`` and the
frames of ``--video``. It avoids matplotlib on purpose: a matplotlib figure per window costs several
times the segmentation of a sparse window, while NumPy images, OpenCV lines and text and OpenCV's PNG
encoder take a few milliseconds a window (README, "Output files").

Design, in the order the image is built:

* **Crop**: the panels show the events' extent (2nd-998th per mille of the raw and the compensated
  positions, so a few stray noise events do not widen it) plus a margin, not the whole sensor; video
  frames pass ``crop=False`` so that every frame has the same size.
* **Scale**: each panel's longer side is :data:`PANEL_SIDE` pixels whatever the crop, nearest-neighbour
  when enlarging (pixels stay visible), area-averaged when shrinking.
* **Layout**: the grid of panels (rows x columns) whose overall shape is closest to 16:9 for the crop's
  aspect ratio, so wide crops stack and tall ones line up.
* **Colours**: a function of the cluster's id (:func:`evseg_torch.viz.render.label_colors`), not of the
  window's cluster order; the id of cluster ``k`` is ``ids[k]``, ``k`` itself by default. A legend
  under the panels names each id with its event count, grey (no cluster) and white (no events).
* **Title**: the caller's title, then the window's time span (first and last event, seconds), then
  any metrics.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from evseg_torch.errors import ShapeError
from evseg_torch.viz.render import UNLABELLED, label_colors, render_event_image, render_labels

PANEL_SIDE = 400  # px, the longer side of each panel
# Panels by name: the paper's Fig. 1 (a)-(d), the ground truth, and the raw events coloured by cluster.
FIG1_PANELS = ("raw", "tracks", "clusters", "segmented")
VIDEO_PANELS = ("labelled", "segmented")
_TITLES = {
    "raw": "(a) raw events",
    "tracks": "(b) feature tracks",
    "clusters": "(c) feature clusters",
    "segmented": "(d) segmented, compensated",
    "labelled": "raw events by cluster",
    "ground_truth": "ground truth (raw events)",
}
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_TEXT_SCALE, _TITLE_SCALE = 0.45, 0.55
_LINE = 22  # px per line of text
_GAP = 6  # px between panels
_TRACK = (215, 25, 25)
_INK = (20, 20, 20)


def render_fig1(
    segmentation,
    title: str | None = None,
    metrics: dict | None = None,
    ground_truth: np.ndarray | None = None,
    ids: np.ndarray | None = None,
    panels: tuple[str, ...] = FIG1_PANELS,
    crop: bool = True,
) -> np.ndarray:
    """Draw one window's panels, title and legend (module doc) as an RGB image.

    Args:
        segmentation: a :class:`~evseg_torch.pipeline.Segmentation` (NumPy arrays).
        title: first line of the title, e.g. ``"window 12"``.
        metrics: optional name -> value pairs, printed on the title's last line.
        ground_truth: optional true layer of each event, :math:`(N,)` (colours as ids); adds the panel
            ``"ground_truth"``.
        ids: the id of each cluster, :math:`(K,)` non-negative integers; colours follow ids.
        panels: which panels, in order: names from ``raw``, ``tracks``, ``clusters``, ``segmented``,
            ``labelled``.
        crop: show the events' extent (True) or the whole sensor (False: same size for every window).

    Returns:
        uint8 :math:`(H_{fig}, W_{fig}, 3)` RGB.

    Raises:
        ShapeError: ``ids`` or ``ground_truth`` do not match the segmentation, or a panel name is unknown.
    """
    height, width = segmentation.sensor_size
    events = segmentation.events
    raw_xy = np.column_stack([events["x"], events["y"]]).astype(np.float64)
    warped_xy = np.asarray(segmentation.warped_xy, dtype=np.float64)
    labels = np.asarray(segmentation.labels, dtype=np.int64)
    n_clusters = int(segmentation.models.shape[0])
    ids = np.arange(n_clusters) if ids is None else np.asarray(ids, dtype=np.int64)
    if ids.shape != (n_clusters,) or np.any(ids < 0):
        raise ShapeError(f"ids must be {n_clusters} non-negative integers, one per cluster, got {ids.shape}")
    event_ids = np.where(labels >= 0, ids[np.clip(labels, 0, None)], -1) if n_clusters else labels
    if ground_truth is not None:
        ground_truth = np.asarray(ground_truth, dtype=np.int64)
        if ground_truth.shape != labels.shape:
            raise ShapeError(
                f"ground_truth must be one label per event {labels.shape}, got {ground_truth.shape}"
            )
        panels = (*panels, "ground_truth")
    x0, y0, x1, y1 = _extent((raw_xy, warped_xy), (height, width)) if crop else (0, 0, width, height)
    size = (y1 - y0, x1 - x0)
    scale = PANEL_SIDE / max(size)
    panel_shape = (max(round(size[0] * scale), 1), max(round(size[1] * scale), 1))
    origin = np.array([x0, y0], dtype=np.float64)

    def resized(image: np.ndarray) -> np.ndarray:
        interpolation = cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA
        return cv2.resize(image, panel_shape[::-1], interpolation=interpolation)

    raw = resized(render_event_image(raw_xy - origin, size))
    images = []
    for name in panels:
        if name == "raw":
            image = raw
        elif name in ("tracks", "clusters"):
            image = np.ascontiguousarray(127 + raw // 2)  # the raw events, faded
            _draw_tracks(image, segmentation, origin, scale, by_cluster=name == "clusters")
        elif name == "segmented":
            image = resized(render_labels(warped_xy - origin, event_ids, size))
        elif name == "labelled":
            image = resized(render_labels(raw_xy - origin, event_ids, size))
        elif name == "ground_truth":
            image = resized(render_labels(raw_xy - origin, ground_truth, size))
        else:
            raise ShapeError(f"unknown panel {name!r}; choose from {sorted(_TITLES)}")
        images.append((_TITLES[name], image))
    counts = np.bincount(labels[labels >= 0], minlength=n_clusters)
    header = [title or "", _time_span(events)]
    if metrics:
        header.append("   ".join(f"{k}: {_fmt(v)}" for k, v in metrics.items()))
    return _compose(images, header, _legend_items(ids, counts))


def write_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an RGB uint8 image as PNG with OpenCV's encoder, tuned for speed.

    PNG's adaptive row filters cost most of the time of writing a figure, and the figures are mostly
    white: without the filters and at zlib level 1, a figure is written several times as fast for a few
    more bytes.
    """
    path = Path(path)
    options = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV 4.11+; older ones filter adaptively (same image, slower)
        options += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    if not cv2.imwrite(str(path), image[..., ::-1], options):
        raise OSError(f"could not write {path}")
    return path


def _extent(positions, sensor_size: tuple[int, int], margin: float = 0.08) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (end exclusive) holding the events, widened by ``margin`` of its size."""
    height, width = sensor_size
    xy = np.concatenate([p[np.isfinite(p).all(axis=1)] for p in positions])
    if len(xy) == 0:
        return 0, 0, width, height
    low, high = np.quantile(xy, [0.002, 0.998], axis=0)
    pad = np.maximum(margin * (high - low), 4.0)
    x0, y0 = np.maximum(np.floor(low - pad), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(high + pad) + 1, [width, height]).astype(int)
    return int(x0), int(y0), int(max(x1, x0 + 1)), int(max(y1, y0 + 1))


def _draw_tracks(image: np.ndarray, segmentation, origin: np.ndarray, scale: float, by_cluster: bool) -> None:
    """Draw level one's tracks (segment from start to end, dot at the start) onto a panel in place."""
    tracks = segmentation.feature_tracks
    if len(tracks.src) == 0:
        return
    # Fixed-point coordinates (4 fractional bits) of pixel centres on the scaled panel.
    src = np.rint(((tracks.src - origin + 0.5) * scale - 0.5) * 16).astype(np.int32)
    dst = np.rint(((tracks.dst - origin + 0.5) * scale - 0.5) * 16).astype(np.int32)
    groups = np.asarray(segmentation.feature_labels) if by_cluster else np.zeros(len(src), dtype=np.int64)
    radius = 24  # 1.5 px
    for group in np.unique(groups):
        chosen = groups == group
        colour = tuple(int(c) for c in label_colors(np.array([group]))[0]) if by_cluster else _TRACK
        lines = np.stack([src[chosen], dst[chosen]], axis=1)
        cv2.polylines(image, list(lines), False, colour, 1, cv2.LINE_AA, shift=4)
        for point in src[chosen]:
            cv2.circle(image, (int(point[0]), int(point[1])), radius, colour, -1, cv2.LINE_AA, shift=4)


def _legend_items(ids: np.ndarray, counts: np.ndarray) -> list[tuple[tuple[int, int, int], str]]:
    order = np.argsort(ids, kind="stable")
    items = [
        (tuple(int(c) for c in label_colors(ids[k : k + 1])[0]), f"{ids[k]}: {counts[k]} ev") for k in order
    ]
    return [*items, (tuple(int(c) for c in UNLABELLED), "no cluster"), ((255, 255, 255), "no events")]


def _compose(images, header: list[str], legend) -> np.ndarray:
    """Lay the titled panels out in a grid under the header lines and over a one-line legend."""
    panel_h, panel_w = images[0][1].shape[:2]
    cell_h = panel_h + _LINE
    rows = min(
        range(1, len(images) + 1),
        key=lambda r: abs(math.log(math.ceil(len(images) / r) * panel_w / (r * cell_h) / (16 / 9))),
    )
    columns = math.ceil(len(images) / rows)
    width = max(columns * panel_w + (columns + 1) * _GAP, 360)
    top = len(header) * _LINE + _GAP
    canvas = np.full((top + rows * (cell_h + _GAP) + _LINE + _GAP, width, 3), 255, dtype=np.uint8)
    for line, text in enumerate(header):
        _text(canvas, text, (_GAP, (line + 1) * _LINE - 6), _TITLE_SCALE if line == 0 else _TEXT_SCALE)
    for index, (name, image) in enumerate(images):
        row, column = divmod(index, columns)
        x, y = _GAP + column * (panel_w + _GAP), top + row * (cell_h + _GAP)
        _text(canvas, name, (x, y + _LINE - 7), _TEXT_SCALE)
        canvas[y + _LINE : y + cell_h, x : x + panel_w] = image
        cv2.rectangle(canvas, (x - 1, y + _LINE - 1), (x + panel_w, y + cell_h), (200, 200, 200), 1)
    _draw_legend(canvas, legend, canvas.shape[0] - _LINE)
    return canvas


def _draw_legend(canvas: np.ndarray, items, top: int) -> None:
    """One line of colour swatches and names; items that do not fit are counted as ``+n more``."""
    x, width = _GAP, canvas.shape[1]
    for index, (colour, name) in enumerate(items):
        text_w = cv2.getTextSize(name, _FONT, _TEXT_SCALE, 1)[0][0]
        if x + 14 + text_w + 90 > width and index < len(items) - 2:
            _text(canvas, f"+{len(items) - 2 - index} more", (x, top + 15), _TEXT_SCALE)
            break
        cv2.rectangle(canvas, (x, top + 4), (x + 12, top + 16), colour, -1)
        cv2.rectangle(canvas, (x, top + 4), (x + 12, top + 16), (120, 120, 120), 1)
        _text(canvas, name, (x + 16, top + 15), _TEXT_SCALE)
        x += 16 + text_w + 14


def _text(canvas: np.ndarray, text: str, at: tuple[int, int], scale: float) -> None:
    cv2.putText(canvas, text, at, _FONT, scale, _INK, 1, cv2.LINE_AA)


def _time_span(events: np.ndarray) -> str:
    if len(events) == 0:
        return "no events"
    first, last = int(events["t"][0]), int(events["t"][-1])
    return f"t {first / 1e6:.4f}-{last / 1e6:.4f} s ({(last - first) / 1e3:.1f} ms, {len(events)} events)"


def _fmt(value) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)
