"""Event recordings in PyTorch training pipelines.

:class:`EventWindowDataset` serves the windows of one recording (any format :mod:`evseg_torch.io`
reads) lazily and with bounded memory, with optional per-event ground-truth labels;
:func:`collate_events` is its DataLoader ``collate_fn`` (the padded batch form is documented in
:mod:`evseg_torch.data.collate`); :class:`SegmentEvents` is a tonic transform that adds each event's
cluster to a sample.

Examples:
    >>> from torch.utils.data import DataLoader
    >>> loader = DataLoader(EventWindowDataset("events.npz", window_ms=30),  # doctest: +SKIP
    ...                     batch_size=8, num_workers=2, collate_fn=collate_events)
"""

from evseg_torch.data.collate import collate_events
from evseg_torch.data.dataset import EventWindowDataset
from evseg_torch.data.transforms import SegmentEvents

__all__ = ["EventWindowDataset", "SegmentEvents", "collate_events"]
