"""Figures: event images, label colours and the paper's Fig. 1 panels.

The image functions return uint8 RGB arrays (NumPy only); :func:`fig1_figure` draws them with
matplotlib, the ``viz`` extra, imported only when a figure is made. Conventions follow the field:
images of events are drawn dark on white, clusters in fixed, distinct colours (label ``k`` always
gets colour ``k``), unlabelled events in grey.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError
from evseg_torch.event_images import event_counts

# Okabe-Ito-like palette, readable for colour-blind viewers; label k takes colour k mod 10.
PALETTE = np.array(
    [
        [0, 114, 178],
        [213, 94, 0],
        [0, 158, 115],
        [204, 121, 167],
        [230, 159, 0],
        [86, 180, 233],
        [240, 228, 66],
        [120, 60, 160],
        [140, 140, 140],
        [0, 0, 0],
    ],
    dtype=np.uint8,
)
UNLABELLED = np.array([190, 190, 190], dtype=np.uint8)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """RGB colour of each label, :math:`(N, 3)` uint8; negative labels are grey."""
    labels = np.asarray(labels)
    colours = PALETTE[np.mod(labels, len(PALETTE))]
    colours[labels < 0] = UNLABELLED
    return colours


def count_image(xy: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Events per pixel of rounded positions, :math:`(H, W)` float64; positions outside are dropped."""
    return event_counts(xy, sensor_size).astype(np.float64)


def render_event_image(xy: np.ndarray, sensor_size: tuple[int, int], saturation: float = 0.99) -> np.ndarray:
    """Grey image of events, dark where many events fall, :math:`(H, W, 3)` uint8."""
    counts = count_image(xy, sensor_size)
    top = np.quantile(counts[counts > 0], saturation) if np.any(counts > 0) else 1.0
    grey = 255 - np.clip(counts / max(top, 1e-9), 0, 1) * 255
    return np.repeat(grey.astype(np.uint8)[..., None], 3, axis=2)


def render_labels(xy: np.ndarray, labels: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Colour each pixel by the label most of its events carry, white where none fall, :math:`(H, W, 3)`."""
    shifted = np.asarray(labels, dtype=np.int64) + 1  # -1 (unlabelled) becomes 0
    votes = event_counts(xy, sensor_size, shifted, n_labels=int(shifted.max(initial=0)) + 1)
    image = label_colors(votes.argmax(axis=0) - 1)
    image[votes.sum(axis=0) == 0] = 255
    return image


def fig1_figure(
    segmentation,
    title: str | None = None,
    metrics: dict | None = None,
    ground_truth: np.ndarray | None = None,
):
    """The paper's Fig. 1 panels for one window, as a matplotlib figure.

    Panels: (a) raw image of events, (b) feature tracks, (c) feature clusters, (d) the segmented,
    motion-compensated image of events (each event warped by its own cluster's model).

    Args:
        segmentation: a :class:`~evseg_torch.pipeline.Segmentation`.
        title: figure title.
        metrics: optional name → value pairs printed under the title (e.g. accuracy against ground truth).
        ground_truth: optional true layer of each event, :math:`(N,)`; adds a fifth panel of the raw
            events coloured by it.
    """
    plt = _pyplot()
    sensor_size = segmentation.sensor_size
    raw = render_event_image(
        np.column_stack([segmentation.events["x"], segmentation.events["y"]]), sensor_size
    )
    tracks = segmentation.feature_tracks
    n_panels = 4 if ground_truth is None else 5
    fig, axes = plt.subplots(1, n_panels, figsize=(4 * n_panels, 3.6), constrained_layout=True)
    axes[0].imshow(raw)
    axes[0].set_title("(a) raw events")
    for ax, colour_by_cluster, name in (
        (axes[1], False, "(b) feature tracks"),
        (axes[2], True, "(c) feature clusters"),
    ):
        ax.imshow(raw, alpha=0.5)
        colours = (
            label_colors(segmentation.feature_labels) / 255.0
            if colour_by_cluster
            else np.tile([[0.85, 0.1, 0.1]], (len(tracks.src), 1))
        )
        for (x0, y0), (x1, y1), colour in zip(tracks.src, tracks.dst, colours, strict=True):
            ax.plot([x0, x1], [y0, y1], color=colour, linewidth=1.2)
        ax.scatter(tracks.src[:, 0], tracks.src[:, 1], s=6, c=colours)
        ax.set_title(name)
    axes[3].imshow(render_labels(segmentation.warped_xy, segmentation.labels, sensor_size))
    axes[3].set_title(f"(d) segmented, compensated ({len(segmentation.models)} clusters)")
    if ground_truth is not None:
        raw_xy = np.column_stack([segmentation.events["x"], segmentation.events["y"]])
        axes[4].imshow(render_labels(raw_xy, ground_truth, sensor_size))
        axes[4].set_title("ground truth (raw events)")
    for ax in axes:
        ax.set_axis_off()
    header = title or ""
    if metrics:
        header += ("\n" if header else "") + "   ".join(f"{k}: {_fmt(v)}" for k, v in metrics.items())
    if header:
        fig.suptitle(header)
    return fig


def boxes_figure(panels: list[dict], title: str | None = None, columns: int = 5):
    """A grid of segmented, compensated windows with a ground-truth and a predicted box on each.

    Args:
        panels: one dict per window with ``image`` (:math:`(H, W, 3)` uint8, e.g. from
            :func:`render_labels`), ``gt_box`` and ``predicted_box`` (``[x, y, w, h]``; NaN for none)
            and ``title``.
        title: figure title.
        columns: panels per row.

    Returns:
        A matplotlib figure: ground truth in red, prediction dashed in black.
    """
    if not panels:
        raise EvsegError("boxes_figure needs at least one panel")
    plt = _pyplot()
    from matplotlib.patches import Rectangle

    columns = min(columns, len(panels))
    rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(
        rows, columns, figsize=(3.2 * columns, 2.6 * rows), squeeze=False, constrained_layout=True
    )
    for ax in axes.flat:
        ax.set_axis_off()
    for ax, panel in zip(axes.flat, panels, strict=False):
        ax.imshow(panel["image"])
        for box, style in (
            (panel["gt_box"], {"ec": "red"}),
            (panel["predicted_box"], {"ec": "k", "ls": "--"}),
        ):
            if np.all(np.isfinite(box)):
                ax.add_patch(Rectangle(box[:2], box[2], box[3], fill=False, linewidth=1.5, **style))
        ax.set_title(panel["title"], fontsize=9)
    if title:
        fig.suptitle(title)
    return fig


def save_figure(fig, path: str | Path, dpi: int = 80) -> Path:
    """Save a figure as PNG and close it."""
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError:
        raise EvsegError("figures need matplotlib: pip install 'evseg-torch[viz]'") from None
    return plt


def _fmt(value) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)
