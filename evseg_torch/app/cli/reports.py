"""The evaluation commands' shared output: the summary lines of a scene benchmark, and JSON files."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("evseg")


def summary_line(summary: dict) -> str:
    """The ``mean:`` line of a scene benchmark, from :func:`~evseg_torch.evaluation.synthetic.summarize`."""
    return (
        f"mean: accuracy {summary['accuracy']:.3f}, IMO IoU {summary['iou']:.3f}, "
        f"detection {summary['detection']:.3f}, "
        f"cluster-count error {summary['count_error']:+.2f} (|.| {summary['abs_count_error']:.2f}), "
        f"median {summary['time_ms_median']:.0f} ms per window"
    )


def misses_line(summary: dict) -> str:
    """How many objects were missed, and why (:func:`~evseg_torch.evaluation.metrics.object_outcomes`)."""
    from evseg_torch.evaluation.metrics import OUTCOMES

    misses = {outcome: int(summary[f"missed_{outcome}"]) for outcome in OUTCOMES[1:]}
    reasons = ", ".join(f"{count} {reason}" for reason, count in misses.items() if count)
    return f"missed objects: {sum(misses.values())}" + (f" ({reasons})" if reasons else "")


def write_json(path: Path | None, data) -> None:
    if path is not None:
        path.write_text(json.dumps(data, indent=2, default=json_default))
        log.info("wrote %s", path)


def json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")
