"""Figures: event images, label colours and the paper's Fig. 1 panels.

The image functions return uint8 RGB arrays (NumPy only); :mod:`evseg_torch.panels` lays them out
as Fig. 1 with OpenCV, and :func:`fig1_figure` and :func:`boxes_figure` show them with matplotlib, the
``viz`` extra, imported only when a figure is made. Conventions follow the field: images of events are
drawn dark on white, clusters in fixed, distinct colours that depend on the id alone (id ``k`` always
gets the same colour, in every window), unlabelled events in grey.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError
from evseg_torch.events.images import event_counts

# Okabe-Ito-like palette, readable for colour-blind viewers, for ids 0-9; higher ids step round the hue
# circle by the golden angle, so neighbouring ids differ.
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
    """RGB colour of each label (a cluster or object id), :math:`(N, 3)` uint8; negative labels are grey."""
    labels = np.asarray(labels, dtype=np.int64)
    colours = PALETTE[np.clip(labels, 0, len(PALETTE) - 1)]
    beyond = labels >= len(PALETTE)
    if np.any(beyond):
        hue = np.mod((labels[beyond] - len(PALETTE)) * 137.508, 360.0) / 60.0
        # Saturated, mid-bright colours (HSV with S = 0.75, V = 0.8), away from grey and white.
        high, low = 0.8 * 255, 0.2 * 255
        mid = low + (high - low) * (1 - np.abs(np.mod(hue, 2) - 1))
        sector = hue.astype(np.int64) % 6
        table = np.array([[0, 1, 2], [1, 0, 2], [2, 0, 1], [2, 1, 0], [1, 2, 0], [0, 2, 1]])[sector]
        values = np.stack([np.full_like(mid, high), mid, np.full_like(mid, low)], axis=1)
        colours[beyond] = np.rint(np.take_along_axis(values, table, axis=1)).astype(np.uint8)
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
    """The paper's Fig. 1 panels for one window (:func:`evseg_torch.panels.render_fig1`) as a matplotlib
    figure, e.g. to show in a notebook; to write a PNG, use ``render_fig1`` and ``write_png`` instead.

    Panels: (a) raw image of events, (b) feature tracks, (c) feature clusters, (d) the segmented,
    motion-compensated image of events (each event warped by its own cluster's model).

    Args:
        segmentation: a :class:`~evseg_torch.pipeline.Segmentation`.
        title: figure title.
        metrics: optional name → value pairs printed under the title (e.g. accuracy against ground truth).
        ground_truth: optional true layer of each event, :math:`(N,)`; adds a fifth panel of the raw
            events coloured by it.
    """
    from evseg_torch.panels import render_fig1

    image = render_fig1(
        segmentation, title=title, metrics=metrics, ground_truth=ground_truth, ids=segmentation.object_ids
    )
    plt = _pyplot()
    fig = plt.figure(figsize=(image.shape[1] / 100, image.shape[0] / 100), dpi=100)
    fig.figimage(image)
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
