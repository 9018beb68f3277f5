"""Windows cut from a stream of events, by time or by count, chunk by chunk."""

import numpy as np
import pytest

from evseg_torch.data import EventWindowDataset
from evseg_torch.errors import EventFormatError
from evseg_torch.events import (
    CountWindowIndex,
    TimeWindowIndex,
    as_events,
    iter_windows,
    window_ranges_by_count,
    window_ranges_by_time,
)


class TestWindows:
    def test_by_time_covers_each_event_once_without_overlap(self):
        t = np.sort(np.random.default_rng(0).integers(0, 100_000, 1000))
        ranges = window_ranges_by_time(t, window_ms=10)
        assert ranges[0, 0] == 0 and ranges[-1, 1] == len(t)
        np.testing.assert_array_equal(ranges[1:, 0], ranges[:-1, 1])
        for begin, end in ranges:
            assert end == begin or np.ptp(t[begin:end]) < 10_000

    def test_by_time_stride_and_start(self):
        t = np.arange(0, 50_000, 100)
        ranges = window_ranges_by_time(t, window_ms=20, stride_ms=10, start_us=10_000)
        assert t[ranges[0, 0]] == 10_000
        assert ranges[0, 1] - ranges[0, 0] == 200
        assert len(ranges) == 4

    def test_by_count(self):
        np.testing.assert_array_equal(window_ranges_by_count(10, 4), [[0, 4], [4, 8], [8, 10]])
        # One last partial window, as iter_windows cuts them; [4, 5] is no longer a window of its own.
        np.testing.assert_array_equal(window_ranges_by_count(5, 4, stride=2), [[0, 4], [2, 5]])
        with pytest.raises(EventFormatError, match="events_per_window must be a positive whole number"):
            window_ranges_by_count(10, 0)
        with pytest.raises(EventFormatError, match="stride must be a positive whole number"):
            window_ranges_by_count(10, 4, stride=0)
        with pytest.raises(EventFormatError, match="n_events must be at least 0"):
            window_ranges_by_count(-1, 4)
        with pytest.raises(EventFormatError, match="window_ms must be positive"):
            window_ranges_by_time(np.arange(3), window_ms=0)
        with pytest.raises(EventFormatError, match="stride_ms must be positive"):
            window_ranges_by_time(np.arange(3), window_ms=1, stride_ms=0)
        with pytest.raises(EventFormatError, match="decrease at event 2"):
            window_ranges_by_time(np.array([0, 5, 3]), window_ms=1)

    @pytest.mark.parametrize(
        ("n_events", "size", "stride", "last"),
        [(3000, 300, 120, [2760, 3000]), (600, 100, 250, [500, 600]), (520, 100, 250, [500, 520])],
    )
    def test_by_count_full_windows_then_one_partial(self, n_events, size, stride, last):
        ranges = window_ranges_by_count(n_events, size, stride)
        assert ranges[-1].tolist() == last
        np.testing.assert_array_equal(ranges[:-1, 0], stride * np.arange(len(ranges) - 1))
        assert np.all(np.diff(ranges[:-1], axis=1) == size)
        assert len(window_ranges_by_count(3000, 300, 120)) == 24

    def test_by_count_with_nothing_left_after_the_full_windows(self):
        np.testing.assert_array_equal(window_ranges_by_count(450, 100, 250), [[0, 100], [250, 350]])
        assert window_ranges_by_count(0, 4).shape == (0, 2)

    def test_time_index_returns_a_window_once_an_event_reaches_its_end(self):
        index = TimeWindowIndex(window_us=10)
        assert index.add(np.array([0, 4, 9])).shape == (0, 2)
        assert index.add(np.array([10])).tolist() == [[0, 3]]
        assert index.add(np.array([35])).tolist() == [[3, 4], [4, 4]]
        assert index.finish().tolist() == [[4, 5]]
        assert (index.start_us, index.n_windows, index.n_events) == (0, 4, 5)

    def test_index_errors_are_named(self):
        with pytest.raises(EventFormatError, match="window_us must be a positive whole number"):
            TimeWindowIndex(0)
        with pytest.raises(EventFormatError, match="stride_us must be a whole number"):
            TimeWindowIndex(10, 2.5)
        with pytest.raises(EventFormatError, match="stride_events must be a positive whole number"):
            CountWindowIndex(10, -1)
        with pytest.raises(EventFormatError, match="1-D"):
            TimeWindowIndex(10).add(np.zeros((2, 2), dtype=np.int64))
        index = TimeWindowIndex(10)
        index.add(np.array([5, 8]))
        with pytest.raises(EventFormatError, match=r"decrease between chunks \(8 us then 7 us\)"):
            index.add(np.array([7, 9]))
        with pytest.raises(EventFormatError, match=r"decrease at event 4 \(12 us then 11 us\)"):
            index.add(np.array([9, 12, 11]))


class TestIterWindows:
    @staticmethod
    def _stream(n=3000, seed=0):
        t = np.sort(np.random.default_rng(seed).integers(0, 100_000, n))
        return as_events(np.column_stack([t * 1e-6, t % 7, t % 5, t % 2]))

    @pytest.mark.parametrize("chunk", [1, 7, 500, 10_000])
    @pytest.mark.parametrize(("window", "stride"), [(10, None), (10, 4), (7.5, 12)])
    def test_time_windows_match_searchsorted_whatever_the_chunking(self, chunk, window, stride):
        events = self._stream()
        chunks = (events[i : i + chunk] for i in range(0, len(events), chunk))
        got = list(iter_windows(chunks, window_ms=window, stride_ms=stride))
        ranges = window_ranges_by_time(events["t"], window, stride)
        assert [w.index for w in got] == list(range(len(ranges)))
        for w, (begin, end) in zip(got, ranges, strict=True):
            assert w.offset == begin or begin == end
            np.testing.assert_array_equal(w.events, events[begin:end])

    @pytest.mark.parametrize("chunk", [3, 1000])
    def test_count_windows(self, chunk):
        events = self._stream(1000)
        chunks = (events[i : i + chunk] for i in range(0, len(events), chunk))
        got = list(iter_windows(chunks, events_per_window=300, stride_events=200))
        ranges = window_ranges_by_count(len(events), 300, 200)
        assert len(got) == len(ranges)
        for w, (begin, end) in zip(got, ranges, strict=True):
            assert w.offset == begin
            np.testing.assert_array_equal(w.events, events[begin:end])

    def test_count_stride_longer_than_window_across_chunks(self):
        # A chunk that ends mid-stride once moved the offset by the whole stride: window 1 claimed
        # offset 250 but held events 120-219, and 5 windows came instead of 3.
        events = self._stream(600)
        chunks = (events[i : i + 120] for i in range(0, len(events), 120))
        got = list(iter_windows(chunks, events_per_window=100, stride_events=250))
        assert [(w.index, w.offset, len(w.events)) for w in got] == [
            (0, 0, 100),
            (1, 250, 100),
            (2, 500, 100),
        ]
        for w in got:
            np.testing.assert_array_equal(w.events, events[w.offset : w.offset + 100])

    @pytest.mark.parametrize(
        ("geometry", "closing"), [({"window_ms": 10}, 0), ({"events_per_window": 300}, -1)], ids=str
    )
    def test_windows_come_as_soon_as_complete(self, geometry, closing):
        events = self._stream()
        pulled = []

        def chunks():
            for i in range(0, len(events), 100):
                pulled.append(i + 100)
                yield events[i : i + 100]

        for window in iter_windows(chunks(), **geometry):
            end = window.offset + len(window.events)
            if end < len(events):
                # The event that closes the window (the first at or after its end, or its own last)
                # lies in the last chunk read: no later chunk was needed.
                assert pulled[-1] - 100 <= end + closing < pulled[-1]

    def test_errors(self):
        events = self._stream(100)
        with pytest.raises(EventFormatError, match="exactly one"):
            list(iter_windows([events]))
        with pytest.raises(EventFormatError, match="between chunks"):
            list(iter_windows([events[50:], events[:50]], window_ms=5))


RECORDINGS = ("uniform", "gaps", "duplicates", "one_instant", "single_event")
STRIDES = {"smaller": 0.4, "equal": 1.0, "larger": 2.7}
CHUNKINGS = (1, 7, 120, None)  # None: the whole recording as one chunk


def _recording(kind: str, rng: np.random.Generator) -> np.ndarray:
    n = 1 if kind == "single_event" else int(rng.integers(2, 400))
    if kind == "one_instant":
        t = np.full(n, 5_000)
    elif kind == "duplicates":
        t = np.sort(rng.integers(0, 40, n)) * 250
    else:
        t = np.sort(rng.integers(0, 20_000, n))
    if kind == "gaps":
        t[n // 3 :] += 9_000
        t[2 * n // 3 :] += 15_000
    xy = rng.integers(0, 16, (n, 2))
    return as_events(np.column_stack([t * 1e-6, xy, rng.integers(0, 2, n)]))


def _reference_ranges(t_us: np.ndarray, geometry: dict) -> np.ndarray:
    """The windows by their definition, one at a time."""
    if "window_ms" in geometry:
        window_us, stride_us = round(geometry["window_ms"] * 1000), round(geometry["stride_ms"] * 1000)
        starts = range(int(t_us[0]), int(t_us[-1]) + 1, stride_us)
        return np.array([[np.sum(t_us < s), np.sum(t_us < s + window_us)] for s in starts]).reshape(-1, 2)
    size, stride, n_events = geometry["events_per_window"], geometry["stride_events"], len(t_us)
    begins = list(range(0, n_events - size + 1, stride))
    ranges = [[begin, begin + size] for begin in begins]
    next_begin = begins[-1] + stride if begins else 0
    if next_begin < n_events:
        ranges.append([next_begin, n_events])
    return np.array(ranges).reshape(-1, 2)


class TestOneWindowCutting:
    """iter_windows, the whole-array ranges and the dataset cut the same windows, however chunked."""

    @pytest.mark.parametrize("by", ["time", "count"])
    @pytest.mark.parametrize("stride", list(STRIDES))
    @pytest.mark.parametrize("recording", RECORDINGS)
    def test_same_windows_everywhere(self, tmp_path, recording, stride, by):
        seed = [RECORDINGS.index(recording), list(STRIDES).index(stride), by == "time"]
        rng = np.random.default_rng(seed)
        events = _recording(recording, rng)
        if by == "time":
            window_ms = float(rng.choice([0.25, 1.0, 2.2]))
            geometry = {"window_ms": window_ms, "stride_ms": window_ms * STRIDES[stride]}
            whole = window_ranges_by_time(events["t"], geometry["window_ms"], geometry["stride_ms"])
        else:
            size = int(rng.choice([1, 7, 50]))
            geometry = {"events_per_window": size, "stride_events": max(1, round(size * STRIDES[stride]))}
            whole = window_ranges_by_count(len(events), size, geometry["stride_events"])
        np.testing.assert_array_equal(whole, _reference_ranges(events["t"], geometry))
        path = tmp_path / "events.npy"
        np.save(path, events)
        for chunk in CHUNKINGS:
            size = chunk or len(events)
            chunks = (events[i : i + size] for i in range(0, len(events), size))
            windows = list(iter_windows(chunks, **geometry))
            assert [w.index for w in windows] == list(range(len(whole))), chunk
            for window, (begin, end) in zip(windows, whole, strict=True):
                assert (window.offset, window.offset + len(window.events)) == (begin, end), chunk
                np.testing.assert_array_equal(window.events, events[begin:end])
            dataset = EventWindowDataset(path, chunk_size=size, **geometry)
            np.testing.assert_array_equal(dataset.windows, whole)
