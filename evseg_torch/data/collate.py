"""The DataLoader ``collate_fn`` of evseg_torch: windows of different lengths into one padded batch.

:func:`collate_events` turns B items of :class:`~evseg_torch.data.EventWindowDataset` (or B
single-window :class:`~evseg_torch.events.EventBatch` objects) into this batch:

===============  ===========================================================================
key              value
===============  ===========================================================================
``events``       padded :class:`~evseg_torch.events.EventBatch` from
                 :func:`~evseg_torch.events.batch_windows`: ``xy`` :math:`(B, N_{max}, 2)`,
                 ``t`` and ``p`` :math:`(B, N_{max})`, ``lengths`` int64 :math:`(B,)`; padding sits
                 at the end of each row, 0 in every field
``labels``       int64 :math:`(B, N_{max})`, ``-1`` in the padding (labelled items only)
``ignore``       bool :math:`(B, N_{max})`, ``True`` in the padding (labelled items only)
``t_start_us``   int64 :math:`(B,)`
``index``        int64 :math:`(B,)`
``sensor_size``  ``(H, W)``, once: every item must share it
===============  ===========================================================================

Padded events are ignored and labelled ``-1``, so a loss that skips ignored events or negative labels
never sees the padding. Keys of other names are collated by :func:`torch.utils.data.default_collate`.
B single-window :class:`~evseg_torch.events.EventBatch` objects collate to the padded batch alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.nn.utils.rnn import pad_sequence
from torch.utils.data import default_collate

from evseg_torch.errors import EventFormatError, ShapeError
from evseg_torch.events import EventBatch, batch_windows

__all__ = ["collate_events"]

# The padding value and dtype of each per-event key.
_PADDING = {"labels": (-1, torch.int64), "ignore": (True, torch.bool)}
_SCALARS = ("t_start_us", "index")


def collate_events(samples: Sequence[dict | EventBatch]) -> dict | EventBatch:
    """Collate window items into the padded batch of the module docstring.

    Args:
        samples: B dicts with at least ``events`` (one window each, as
            :class:`~evseg_torch.data.EventWindowDataset` gives), all with the same keys; or B
            single-window :class:`~evseg_torch.events.EventBatch` objects.

    Returns:
        The batch dict; for EventBatch samples, the padded :class:`~evseg_torch.events.EventBatch`.

    Raises:
        EventFormatError: no samples, samples of mixed kinds or keys, no ``events``, or items of
            different sensor sizes.
        ShapeError: an item's ``labels`` or ``ignore`` is not one value per event.

    Examples:
        >>> one = {"events": EventBatch(torch.zeros(3, 2), torch.zeros(3), torch.ones(3)),
        ...        "labels": torch.tensor([0, 1, 1]), "index": 0, "sensor_size": (90, 120)}
        >>> two = {"events": EventBatch(torch.ones(1, 2), torch.zeros(1), -torch.ones(1)),
        ...        "labels": torch.tensor([2]), "index": 1, "sensor_size": (90, 120)}
        >>> batch = collate_events([one, two])
        >>> batch["events"].lengths.tolist(), batch["labels"].tolist(), batch["index"].tolist()
        ([3, 1], [[0, 1, 1], [2, -1, -1]], [0, 1])
    """
    samples = list(samples)
    if not samples:
        raise EventFormatError("collate_events needs at least one sample, got none")
    if all(isinstance(sample, EventBatch) for sample in samples):
        return batch_windows(samples)
    if not all(isinstance(sample, dict) for sample in samples):
        kinds = sorted({type(sample).__name__ for sample in samples})
        raise EventFormatError(f"samples must all be dicts or all EventBatch windows, got {kinds}")
    keys = list(samples[0])
    for index, sample in enumerate(samples):
        if set(sample) != set(keys):
            raise EventFormatError(f"sample {index} has keys {sorted(sample)}, sample 0 has {sorted(keys)}")
    if "events" not in keys:
        raise EventFormatError(f"samples must hold 'events', got keys {sorted(keys)}")
    events = batch_windows([sample["events"] for sample in samples])
    return {key: _collate_key(key, [sample[key] for sample in samples], events) for key in keys}


def _collate_key(key: str, values: list, events: EventBatch):
    if key == "events":
        return events
    if key in _PADDING:
        return _padded(key, values, events.lengths)
    if key in _SCALARS:
        return torch.as_tensor(values, dtype=torch.int64)
    if key == "sensor_size":
        sizes = {tuple(int(v) for v in size) for size in values}
        if len(sizes) != 1:
            raise EventFormatError(f"a batch must come from one sensor size (H, W), got {sorted(sizes)}")
        return sizes.pop()
    return default_collate(values)


def _padded(key: str, values: list, lengths: torch.Tensor) -> torch.Tensor:
    """Per-event values :math:`(N_b,)` into :math:`(B, N_{max})`, padded with the key's padding value."""
    padding, dtype = _PADDING[key]
    values = [torch.as_tensor(value, dtype=dtype) for value in values]
    for index, (value, count) in enumerate(zip(values, lengths.tolist(), strict=True)):
        if value.shape != (count,):
            raise ShapeError(
                f"sample {index}: {key!r} must hold one value per event, ({count},), got {tuple(value.shape)}"
            )
    return pad_sequence(values, batch_first=True, padding_value=padding)
