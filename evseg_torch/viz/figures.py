"""Matplotlib figures: the paper's Fig. 1 panels of a window, and grids of windows with their boxes.

Matplotlib is the ``viz`` extra, imported only when a figure is made. The images come from
:mod:`evseg_torch.viz.render` and :mod:`evseg_torch.viz.panels`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError
from evseg_torch.viz.panels import render_fig1


def fig1_figure(
    segmentation,
    title: str | None = None,
    metrics: dict | None = None,
    ground_truth: np.ndarray | None = None,
):
    """The paper's Fig. 1 panels for one window (:func:`evseg_torch.viz.panels.render_fig1`) as a matplotlib
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
