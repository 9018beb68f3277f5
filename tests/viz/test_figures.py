"""Matplotlib figures of windows with their boxes."""

import numpy as np
import pytest

from evseg_torch.errors import EvsegError
from evseg_torch.viz.figures import boxes_figure, save_figure


def test_boxes_figure(tmp_path):
    image = np.full((20, 30, 3), 255, dtype=np.uint8)
    panels = [
        {
            "image": image,
            "gt_box": np.array([2.0, 3, 5, 4]),
            "predicted_box": np.array([3.0, 3, 5, 4]),
            "title": "a",
        },
        {
            "image": image,
            "gt_box": np.array([2.0, 3, 5, 4]),
            "predicted_box": np.full(4, np.nan),
            "title": "b",
        },
    ]
    fig = boxes_figure(panels, title="EED", columns=5)
    drawn = [ax for ax in fig.axes if ax.images]
    assert len(drawn) == 2 and [len(ax.patches) for ax in drawn] == [2, 1]  # no box where none matched
    assert drawn[1].get_title() == "b"
    assert save_figure(fig, tmp_path / "boxes.png").stat().st_size > 1000
    with pytest.raises(EvsegError, match="at least one panel"):
        boxes_figure([])
