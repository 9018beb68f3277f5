"""Events: their canonical NumPy form, windows cut from a stream, torch batches, and count images.

* :mod:`~evseg_torch.events.format`: the canonical structured array (:data:`EVENT_DTYPE`), its
  validation (:func:`as_events`) and conversions to other libraries' forms;
* :mod:`~evseg_torch.events.windows`: windows by time or by event count, cut chunk by chunk from a
  stream (:func:`iter_windows`);
* :mod:`~evseg_torch.events.batches`: events as torch tensors, one window or a padded batch
  (:class:`EventBatch`); torch is imported on first use, so NumPy-only code never loads it;
* :mod:`~evseg_torch.events.images`: how many events fall on each pixel (:func:`event_counts`).

The public names of all four are importable from here.
"""

from evseg_torch.events.batches import EventBatch, batch_of_one, batch_windows, to_torch
from evseg_torch.events.format import (
    EVENT_DTYPE,
    as_events,
    check_sensor_size,
    infer_sensor_size,
    sensor_size_from_tonic,
    sensor_size_to_tonic,
    to_array,
)
from evseg_torch.events.images import event_counts
from evseg_torch.events.windows import (
    CountWindowIndex,
    TimeWindowIndex,
    Window,
    iter_windows,
    window_ranges_by_count,
    window_ranges_by_time,
)

__all__ = [
    "EVENT_DTYPE",
    "CountWindowIndex",
    "EventBatch",
    "TimeWindowIndex",
    "Window",
    "as_events",
    "batch_of_one",
    "batch_windows",
    "check_sensor_size",
    "event_counts",
    "infer_sensor_size",
    "iter_windows",
    "sensor_size_from_tonic",
    "sensor_size_to_tonic",
    "to_array",
    "to_torch",
    "window_ranges_by_count",
    "window_ranges_by_time",
]
