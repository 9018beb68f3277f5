"""evseg_torch: event-camera motion segmentation by cascaded two-level multi-model fitting.

``CascadedSegmenter`` and ``Segmentation`` load torch on first use, so that NumPy-only parts (level
one, io, the metrics) import without it.
"""

from evseg_torch.app.results import SegmentationResults, load_results
from evseg_torch.config import SegmenterConfig, load_config
from evseg_torch.errors import (
    ConfigError,
    EventFormatError,
    EvsegError,
    ModelError,
    ReaderError,
    ResultsError,
    ShapeError,
)
from evseg_torch.events import EVENT_DTYPE, EventBatch, as_events, batch_windows, to_torch
from evseg_torch.io import load_events
from evseg_torch.version import __version__

_LAZY = {"CascadedSegmenter", "Segmentation"}


def __getattr__(name: str):
    if name in _LAZY:
        from evseg_torch import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'evseg_torch' has no attribute {name!r}")


__all__ = [
    "EVENT_DTYPE",
    "CascadedSegmenter",
    "ConfigError",
    "EventBatch",
    "EventFormatError",
    "EvsegError",
    "ModelError",
    "ReaderError",
    "ResultsError",
    "Segmentation",
    "SegmentationResults",
    "SegmenterConfig",
    "ShapeError",
    "__version__",
    "as_events",
    "batch_windows",
    "load_config",
    "load_events",
    "load_results",
    "to_torch",
]
