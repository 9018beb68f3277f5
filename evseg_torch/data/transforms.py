"""A tonic transform that segments a sample's events and adds each event's cluster as a field.

tonic (``pip install evseg-torch[tonic]``) passes a sample's events from transform to transform as a
NumPy structured array with fields ``x``, ``y``, ``t`` (integer microseconds) and ``p`` (bool or int),
in any field order and with any extra fields. :class:`SegmentEvents` takes such an array and returns a
new one with the same fields plus an integer cluster field, so it chains with tonic's other transforms
in ``tonic.transforms.Compose``. It needs no import of tonic itself.
"""

from __future__ import annotations

import numpy as np

from evseg_torch.config import SegmenterConfig
from evseg_torch.errors import ConfigError, EventFormatError
from evseg_torch.events import as_events, sensor_size_from_tonic, sensor_size_to_tonic
from evseg_torch.pipeline import CascadedSegmenter

__all__ = ["SegmentEvents"]


class SegmentEvents:
    """Segment a tonic sample with a :class:`~evseg_torch.pipeline.CascadedSegmenter`.

    A sample shorter than the config's window is one window. A longer one is cut into consecutive,
    non-overlapping windows of the config (``window_ms``, or ``events_per_window``; its ``stride_ms`` is
    not used, so that every event lies in exactly one window) and segmented window by window with
    :meth:`~evseg_torch.pipeline.CascadedSegmenter.stream`, each window's models seeding the next.
    Clusters are numbered apart across windows: window ``w``'s clusters follow those of the windows
    before it. Events of a window with fewer than the config's ``min_events`` get ``-1``.

    Args:
        sensor_size: tonic's ``(W, H, P)`` of the samples, to build a segmenter from ``config``.
        segmenter: a segmenter to use instead (give exactly one of ``sensor_size`` and ``segmenter``).
        config: the built segmenter's :class:`~evseg_torch.config.SegmenterConfig`; defaults to the
            built-in defaults.
        field: the name of the added field; an existing field of that name is overwritten.

    Shape:
        - Input: structured :math:`(N,)` with fields ``x``, ``y``, ``t`` (integer µs, non-decreasing)
          and ``p``/``on``/``polarity``, and any others.
        - Output: a new structured :math:`(N,)`, the input's fields and values plus ``field`` int64.

    Raises:
        ConfigError: not exactly one of ``sensor_size`` and ``segmenter``, or ``config`` given with
            ``segmenter``.

    Examples:
        >>> from evseg_torch.synthetic import make_scene
        >>> events = make_scene((90, 120), 0.03, n_objects=1, rng=0).events
        >>> segment = SegmentEvents(sensor_size=(120, 90, 2))
        >>> out = segment(events)
        >>> out.dtype.names, len(out) == len(events), bool((out["label"] >= 0).all())
        (('t', 'x', 'y', 'p', 'label'), True, True)
    """

    def __init__(
        self,
        sensor_size: tuple[int, int, int] | None = None,
        *,
        segmenter: CascadedSegmenter | None = None,
        config: SegmenterConfig | None = None,
        field: str = "label",
    ) -> None:
        if (sensor_size is None) == (segmenter is None):
            raise ConfigError("give exactly one of sensor_size (tonic's (W, H, P)) and segmenter")
        if segmenter is not None and config is not None:
            raise ConfigError("config configures a segmenter built from sensor_size; configure yours instead")
        if segmenter is None:
            segmenter = CascadedSegmenter(sensor_size_from_tonic(sensor_size), config)
        self.segmenter = segmenter
        self.field = field

    def __call__(self, events: np.ndarray) -> np.ndarray:
        """Segment ``events`` (see Shape) and return them with the cluster field added.

        Raises:
            EventFormatError: ``events`` is not a 1-D structured array, or its events are invalid for
                :func:`~evseg_torch.events.as_events` (e.g. out of order, float ``t``, or outside the
                sensor).
        """
        if not isinstance(events, np.ndarray) or events.dtype.names is None or events.ndim != 1:
            raise EventFormatError(
                "SegmentEvents takes a 1-D structured event array (tonic's form, fields x, y, t, p), "
                f"got {type(events).__name__} of dtype {getattr(events, 'dtype', None)}"
            )
        labels = self._labels(events) if len(events) else np.zeros(0, dtype=np.int64)
        return _with_field(events, self.field, labels)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(sensor_size={sensor_size_to_tonic(self.segmenter.sensor_size)}, "
            f"field={self.field!r})"
        )

    def _labels(self, events: np.ndarray) -> np.ndarray:
        canonical = as_events(events, self.segmenter.sensor_size)
        window = self.segmenter.config.window
        if window.events_per_window is not None:
            geometry = {"events_per_window": window.events_per_window}
        else:
            geometry = {"window_ms": window.window_ms, "stride_ms": window.window_ms}
        labels = np.full(len(canonical), -1, dtype=np.int64)
        first = 0
        for result in self.segmenter.stream(canonical, **geometry):
            own = result.labels
            labels[result.offset : result.offset + len(own)] = np.where(own >= 0, own + first, -1)
            first += len(result.models)
        return labels


def _with_field(events: np.ndarray, field: str, values: np.ndarray) -> np.ndarray:
    """A new structured array: ``events``' fields and ``field`` holding ``values``."""
    names = events.dtype.names
    if field in names:
        out = events.copy()
    else:
        # Field by field, so that a padded input dtype (e.g. expelliarmus') comes out packed.
        out = np.empty(
            len(events), dtype=[*((name, events.dtype[name]) for name in names), (field, np.int64)]
        )
        for name in names:
            out[name] = events[name]
    out[field] = values
    return out
