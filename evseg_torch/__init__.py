"""evseg_torch: event-camera motion segmentation by cascaded two-level multi-model fitting."""

from evseg_torch.errors import ConfigError, EventFormatError, EvsegError, ModelError, ReaderError, ShapeError
from evseg_torch.events import EVENT_DTYPE, EventBatch, as_events, to_torch

__version__ = "0.1.0"

__all__ = [
    "EVENT_DTYPE",
    "ConfigError",
    "EventBatch",
    "EventFormatError",
    "EvsegError",
    "ModelError",
    "ReaderError",
    "ShapeError",
    "__version__",
    "as_events",
    "to_torch",
]
