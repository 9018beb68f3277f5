import gc
import pickle

import numpy as np
import pytest
import torch

from evseg_torch.data import EventWindowDataset
from evseg_torch.errors import ConfigError, EventFormatError, ReaderError
from evseg_torch.evaluation.labelled import load_labelled
from evseg_torch.events import EVENT_DTYPE, EventBatch, iter_windows
from evseg_torch.io import load_events, save_evimo
from tests.helpers.io import HEIGHT, WIDTH, WRITERS, make_events

PROBE = "scene_200.npz"

GEOMETRIES = [
    {"window_ms": 2},
    {"window_ms": 3, "stride_ms": 1},
    {"window_ms": 1, "stride_ms": 2.5},
    {"events_per_window": 300},
    {"events_per_window": 300, "stride_events": 120},
    {"events_per_window": 100, "stride_events": 250},
]


def _with_gap(events: np.ndarray, gap_us: int = 20_000) -> np.ndarray:
    """The events with a silent stretch in the middle, so that some time windows are empty."""
    events = events.copy()
    events["t"][len(events) // 2 :] += gap_us
    return events


def _labelled_npz(path, events, labels, **extra):
    np.savez(path, t_us=events["t"], x=events["x"], y=events["y"], p=events["p"], label=labels, **extra)
    return path


def _assert_same_windows(dataset, path, geometry):
    # Chunks of another size than the dataset's, so that strides cross chunk boundaries differently.
    events = load_events(path)
    expected = list(iter_windows((events[i : i + 97] for i in range(0, len(events), 97)), **geometry))
    assert len(dataset) == len(expected)
    for window in expected:
        item = dataset[window.index]
        begin, end = dataset.windows[window.index]
        assert (begin, end) == (window.offset, window.offset + len(window.events))
        assert len(item["events"]) == len(window.events)
        np.testing.assert_array_equal(
            item["events"].xy.numpy(), np.column_stack([window.events["x"], window.events["y"]])
        )
        np.testing.assert_array_equal(item["events"].p.numpy(), window.events["p"])
        if len(window.events):
            seconds = (window.events["t"] - item["t_start_us"]) * 1e-6
            np.testing.assert_allclose(item["events"].t.numpy(), seconds, atol=1e-7)


@pytest.fixture
def canonical_npy(tmp_path):
    path = tmp_path / "events.npy"
    np.save(path, _with_gap(make_events(3000)))
    return path


@pytest.fixture
def probe(real_data):
    path = real_data.parent / "synthetic_probe" / PROBE
    if not path.is_file():
        pytest.skip(f"probe scene not found at {path}")
    return path


class TestWindows:
    @pytest.mark.parametrize("geometry", GEOMETRIES, ids=str)
    def test_equal_iter_windows(self, canonical_npy, geometry):
        dataset = EventWindowDataset(canonical_npy, chunk_size=257, **geometry)
        _assert_same_windows(dataset, canonical_npy, geometry)

    @pytest.mark.parametrize("writer", sorted(WRITERS))
    @pytest.mark.parametrize("geometry", [GEOMETRIES[1], GEOMETRIES[4]], ids=str)
    def test_every_format(self, tmp_path, writer, geometry):
        name, write, _ = WRITERS[writer]
        path = tmp_path / name
        write(path, _with_gap(make_events(1500)))
        _assert_same_windows(EventWindowDataset(path, chunk_size=400, **geometry), path, geometry)

    def test_real_recording(self, real_data):
        path = real_data / "dvs128_person_walking" / "alex_walking_for_10secs.aedat"
        dataset = EventWindowDataset(path, window_ms=30, stride_ms=20, chunk_size=10_000)
        assert dataset.sensor_size == (128, 128)
        assert dataset.n_events == 125_028
        _assert_same_windows(dataset, path, {"window_ms": 30, "stride_ms": 20})

    @pytest.mark.parametrize("chunk_size", [1, 13, 10_000])
    def test_chunking_does_not_change_the_windows(self, canonical_npy, chunk_size):
        reference = EventWindowDataset(canonical_npy, window_ms=0.7, stride_ms=0.3, chunk_size=3000)
        dataset = EventWindowDataset(canonical_npy, window_ms=0.7, stride_ms=0.3, chunk_size=chunk_size)
        np.testing.assert_array_equal(dataset.windows, reference.windows)

    def test_gap_gives_empty_time_windows(self, canonical_npy):
        dataset = EventWindowDataset(canonical_npy, window_ms=2)
        lengths = np.diff(dataset.windows, axis=1)[:, 0]
        assert (lengths == 0).sum() >= 9
        empty = dataset[int(np.argmin(lengths))]["events"]
        assert empty.xy.shape == (0, 2) and empty.t.shape == (0,)

    def test_time_window_starts(self, canonical_npy):
        dataset = EventWindowDataset(canonical_npy, window_ms=3, stride_ms=1)
        first = int(np.load(canonical_npy)["t"][0])
        starts = [dataset[i]["t_start_us"] for i in range(len(dataset))]
        assert starts == [first + 1000 * i for i in range(len(dataset))]

    def test_count_window_starts_at_its_first_event(self, canonical_npy):
        dataset = EventWindowDataset(canonical_npy, events_per_window=300, stride_events=120)
        t_us = np.load(canonical_npy)["t"]
        assert [dataset[i]["t_start_us"] for i in range(3)] == t_us[[0, 120, 240]].tolist()
        assert dataset[1]["events"].t[0] == 0


class TestItems:
    def test_form(self, canonical_npy):
        dataset = EventWindowDataset(canonical_npy, window_ms=2, sensor_size=(HEIGHT, WIDTH))
        item = dataset[3]
        assert list(item) == ["events", "t_start_us", "index", "sensor_size"]
        events = item["events"]
        assert isinstance(events, EventBatch) and not events.is_batched
        assert events.t.dtype == torch.float32 and events.xy.dtype == torch.float32
        assert 0 <= events.t.min() and events.t.max() < 2e-3
        assert item["index"] == 3 and item["sensor_size"] == (HEIGHT, WIDTH)
        assert isinstance(item["t_start_us"], int)

    def test_negative_and_out_of_range_index(self, canonical_npy):
        dataset = EventWindowDataset(canonical_npy, events_per_window=1000)
        assert dataset[-1]["index"] == len(dataset) - 1
        with pytest.raises(IndexError, match="out of range"):
            dataset[len(dataset)]
        assert len(list(dataset)) == len(dataset)

    def test_sensor_size_inferred_when_the_file_stores_none(self, canonical_npy):
        events = np.load(canonical_npy)
        dataset = EventWindowDataset(canonical_npy, window_ms=5)
        assert dataset.sensor_size == (int(events["y"].max()) + 1, int(events["x"].max()) + 1)


class TestLabels:
    def test_probe_scene(self, probe):
        events, labels, ignore, size = load_labelled(probe)
        dataset = EventWindowDataset(probe, window_ms=4, labelled=True, chunk_size=5000)
        assert dataset.sensor_size == size and dataset.n_events == len(events)
        for item, (begin, end) in zip(dataset, dataset.windows, strict=True):
            assert item["labels"].dtype == torch.int64 and item["ignore"].dtype == torch.bool
            np.testing.assert_array_equal(item["labels"].numpy(), labels[begin:end])
            np.testing.assert_array_equal(item["ignore"].numpy(), ignore[begin:end])
            np.testing.assert_array_equal(item["events"].xy[:, 0].numpy(), events["x"][begin:end])

    def test_written_npz_labels_follow_their_events(self, tmp_path):
        # Each event's label is a function of its own pixel, so any shift between the two shows.
        events = make_events(2000)
        path = _labelled_npz(tmp_path / "l.npz", events, events["x"] % 7, ambiguous=events["y"] % 2 == 0)
        dataset = EventWindowDataset(
            path, events_per_window=128, stride_events=100, labelled=True, chunk_size=300
        )
        for item in dataset:
            xy = item["events"].xy.long()
            np.testing.assert_array_equal(item["labels"].numpy(), xy[:, 0].numpy() % 7)
            np.testing.assert_array_equal(item["ignore"].numpy(), xy[:, 1].numpy() % 2 == 0)

    def test_structured_npy_fields(self, tmp_path):
        events = make_events(1000)
        dtype = [("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1"), ("cls", "u1"), ("skip", "?")]
        data = np.zeros(len(events), dtype=dtype)
        for name in ("t", "x", "y", "p"):
            data[name] = events[name]
        data["cls"], data["skip"] = events["y"] % 5, events["x"] > 60
        np.save(tmp_path / "s.npy", data)
        dataset = EventWindowDataset(
            tmp_path / "s.npy",
            window_ms=3,
            labelled=True,
            label_field="cls",
            ignore_field="skip",
            chunk_size=99,
        )
        for item in dataset:
            xy = item["events"].xy.long()
            np.testing.assert_array_equal(item["labels"].numpy(), xy[:, 1].numpy() % 5)
            np.testing.assert_array_equal(item["ignore"].numpy(), xy[:, 0].numpy() > 60)

    def test_no_ignore_field_ignores_nothing(self, tmp_path):
        events = make_events(300)
        path = _labelled_npz(tmp_path / "l.npz", events, np.zeros(len(events), dtype=np.int8))
        item = EventWindowDataset(path, events_per_window=300, labelled=True)[0]
        assert not item["ignore"].any() and len(item["ignore"]) == 300

    def test_evimo_file_loads_unlabelled(self, tmp_path):
        events = make_events(600)
        masks = np.zeros((2, HEIGHT, WIDTH), dtype=np.uint8)
        path = save_evimo(tmp_path / "evimo.npz", events, masks, events["t"][[0, -1]] * 1e-6)
        dataset = EventWindowDataset(path, events_per_window=200)
        assert dataset.sensor_size == (HEIGHT, WIDTH) and dataset.n_events == 600
        with pytest.raises(ReaderError, match="no per-event label field 'label'"):
            EventWindowDataset(path, events_per_window=200, labelled=True)

    def test_unlabelled_items_have_no_labels(self, tmp_path):
        events = make_events(300)
        path = _labelled_npz(tmp_path / "l.npz", events, np.zeros(len(events), dtype=np.int8))
        assert "labels" not in EventWindowDataset(path, events_per_window=300)[0]


class TestCache:
    def test_canonical_npy_is_read_in_place(self, canonical_npy, tmp_path):
        cache = tmp_path / "cache"
        cache.mkdir()
        dataset = EventWindowDataset(canonical_npy, window_ms=2, cache_dir=cache)
        assert len(dataset) and not any(cache.iterdir())

    def test_cache_is_removed_with_the_dataset(self, tmp_path):
        events = make_events(500)
        path = _labelled_npz(tmp_path / "l.npz", events, np.zeros(len(events), dtype=np.int8))
        cache = tmp_path / "cache"
        cache.mkdir()
        dataset = EventWindowDataset(path, window_ms=2, labelled=True, cache_dir=cache)
        assert len(list(cache.iterdir())) == 1
        del dataset
        gc.collect()
        assert not any(cache.iterdir())

    def test_pickled_copy_reads_but_does_not_own(self, tmp_path):
        events = make_events(500)
        path = _labelled_npz(tmp_path / "l.npz", events, events["x"].astype(np.int64))
        dataset = EventWindowDataset(path, window_ms=2, labelled=True, cache_dir=tmp_path)
        copy = pickle.loads(pickle.dumps(dataset))
        assert torch.equal(copy[2]["labels"], dataset[2]["labels"])
        del copy
        gc.collect()
        assert torch.equal(dataset[2]["events"].xy, EventWindowDataset(path, window_ms=2)[2]["events"].xy)

    def test_failed_pass_leaves_no_cache(self, tmp_path):
        events = make_events(500)
        events["t"][300] = events["t"][0] - 1
        np.savez(tmp_path / "bad.npz", t_us=events["t"], x=events["x"], y=events["y"], p=events["p"])
        cache = tmp_path / "cache"
        cache.mkdir()
        with pytest.raises(EventFormatError, match="decrease"):
            EventWindowDataset(tmp_path / "bad.npz", window_ms=2, cache_dir=cache, chunk_size=100)
        assert not any(cache.iterdir())


class TestErrors:
    def test_missing_file(self, tmp_path):
        with pytest.raises(ReaderError, match="no such file"):
            EventWindowDataset(tmp_path / "absent.npy", window_ms=30)

    def test_cache_dir_not_a_directory(self, tmp_path):
        events = make_events(300)
        path = _labelled_npz(tmp_path / "l.npz", events, np.zeros(300, dtype=np.int8))
        with pytest.raises(ConfigError, match="cache_dir must be an existing directory"):
            EventWindowDataset(path, window_ms=2, cache_dir=tmp_path / "absent")

    @pytest.mark.parametrize(
        "geometry, match",
        [
            ({}, "exactly one of window_ms and events_per_window"),
            ({"window_ms": 30, "events_per_window": 100}, "exactly one of window_ms and events_per_window"),
            ({"window_ms": 0}, "window_ms must be positive"),
            ({"window_ms": -5}, "window_ms must be positive"),
            ({"window_ms": "long"}, "window_ms must be a positive number"),
            ({"window_ms": 30, "stride_ms": 0}, "stride_ms must be positive"),
            ({"events_per_window": 0}, "events_per_window must be an integer of at least 1"),
            ({"events_per_window": 2.5}, "events_per_window must be an integer of at least 1"),
            ({"events_per_window": 10, "stride_events": -1}, "stride_events must be an integer"),
            ({"window_ms": 30, "stride_events": 10}, "stride_events applies to events_per_window"),
            ({"events_per_window": 10, "stride_ms": 10}, "stride_ms applies to window_ms"),
        ],
    )
    def test_window_geometry(self, canonical_npy, geometry, match):
        with pytest.raises(ConfigError, match=match):
            EventWindowDataset(canonical_npy, **geometry)

    def test_missing_label_field(self, tmp_path, canonical_npy):
        events = make_events(300)
        path = _labelled_npz(tmp_path / "l.npz", events, np.zeros(300, dtype=np.int8))
        with pytest.raises(ReaderError, match="no per-event label field 'cls'"):
            EventWindowDataset(path, window_ms=2, labelled=True, label_field="cls")
        with pytest.raises(ReaderError, match="no per-event label field 'label'"):
            EventWindowDataset(canonical_npy, window_ms=2, labelled=True)

    @pytest.mark.parametrize("n_labels", [299, 301])
    def test_labels_of_the_wrong_length(self, tmp_path, n_labels):
        path = _labelled_npz(tmp_path / "l.npz", make_events(300), np.zeros(n_labels, dtype=np.int8))
        with pytest.raises(ReaderError, match=f"holds {n_labels} labels for 300 events"):
            EventWindowDataset(path, window_ms=2, labelled=True, chunk_size=100)

    def test_ignore_flags_of_the_wrong_length(self, tmp_path):
        events = make_events(300)
        path = _labelled_npz(
            tmp_path / "l.npz", events, np.zeros(300, dtype=np.int8), ambiguous=np.zeros(5, bool)
        )
        with pytest.raises(ReaderError, match="1-D of one length"):
            EventWindowDataset(path, window_ms=2, labelled=True)

    def test_float_labels(self, tmp_path):
        path = _labelled_npz(tmp_path / "l.npz", make_events(300), np.zeros(300))
        with pytest.raises(ReaderError, match="must hold integer labels"):
            EventWindowDataset(path, window_ms=2, labelled=True)

    def test_labels_from_a_format_without_them(self, tmp_path):
        name, write, _ = WRITERS["txt"]
        write(tmp_path / name, make_events(100))
        with pytest.raises(
            ReaderError, match=r"labels are read from \.npz members or structured \.npy fields"
        ):
            EventWindowDataset(tmp_path / name, window_ms=2, labelled=True)

    def test_event_outside_the_sensor(self, canonical_npy):
        with pytest.raises(EventFormatError, match="outside the sensor"):
            EventWindowDataset(canonical_npy, window_ms=2, sensor_size=(10, 10))


def test_tonic_structured_npy(tmp_path):
    tonic = pytest.importorskip("tonic")
    events = make_events(800)
    path = tmp_path / "tonic.npy"
    np.save(path, tonic.io.make_structured_array(events["x"], events["y"], events["t"], events["p"] > 0))
    dataset = EventWindowDataset(path, window_ms=2)
    reference = EventWindowDataset(_canonical(tmp_path / "canonical.npy", events), window_ms=2)
    assert len(dataset) == len(reference)
    for mine, theirs in zip(dataset, reference, strict=True):
        assert torch.equal(mine["events"].p, theirs["events"].p)
        assert torch.equal(mine["events"].xy, theirs["events"].xy)


def _canonical(path, events):
    assert events.dtype == EVENT_DTYPE
    np.save(path, events)
    return path
