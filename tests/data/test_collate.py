import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from evseg_torch.data import EventWindowDataset, collate_events
from evseg_torch.errors import EventFormatError, ShapeError
from evseg_torch.events import EventBatch, batch_windows


def _window(n: int, value: float = 1.0) -> EventBatch:
    return EventBatch(torch.full((n, 2), value), torch.linspace(0, 1e-3, n), torch.ones(n))


def _sample(n: int, index: int = 0, sensor_size=(90, 120), **extra) -> dict:
    """An item as EventWindowDataset gives, of ``n`` events labelled 0, 1, ..."""
    return {
        "events": _window(n, index),
        "labels": torch.arange(n),
        "ignore": torch.zeros(n, dtype=torch.bool),
        "t_start_us": 1000 * index,
        "index": index,
        "sensor_size": sensor_size,
        **extra,
    }


@pytest.fixture
def labelled_dataset(tmp_path):
    rng = np.random.default_rng(0)
    n = 4000
    t_us = np.sort(rng.integers(0, 40_000, n))
    x, y = rng.integers(0, 120, n).astype(np.int16), rng.integers(0, 90, n).astype(np.int16)
    p = rng.choice(np.array([-1, 1], dtype=np.int8), n)
    path = tmp_path / "labelled.npz"
    np.savez(
        path, t_us=t_us, x=x, y=y, p=p, label=x % 4 - 1, ambiguous=y < 10, sensor_size=np.array([90, 120])
    )
    return EventWindowDataset(path, window_ms=3, stride_ms=2, labelled=True)


class TestCollate:
    def test_padding_and_lengths(self):
        batch = collate_events([_sample(3, 0), _sample(5, 1), _sample(0, 2)])
        events = batch["events"]
        assert events.lengths.tolist() == [3, 5, 0]
        assert events.xy.shape == (3, 5, 2) and events.t.shape == (3, 5)
        assert batch["labels"].dtype == torch.int64 and batch["ignore"].dtype == torch.bool
        assert batch["labels"].tolist() == [[0, 1, 2, -1, -1], [0, 1, 2, 3, 4], [-1] * 5]
        assert batch["ignore"].tolist() == [[False] * 3 + [True] * 2, [False] * 5, [True] * 5]
        assert torch.equal(batch["ignore"], ~events.mask)
        assert batch["t_start_us"].tolist() == [0, 1000, 2000] and batch["t_start_us"].dtype == torch.int64
        assert batch["index"].dtype == torch.int64
        assert batch["sensor_size"] == (90, 120)

    def test_events_equal_batch_windows(self):
        samples = [_sample(4, 0), _sample(2, 1)]
        expected = batch_windows([sample["events"] for sample in samples])
        events = collate_events(samples)["events"]
        for mine, theirs in zip(events, expected, strict=True):
            assert torch.equal(mine, theirs)

    def test_event_batches_alone(self):
        batch = collate_events([_window(2), _window(4)])
        assert isinstance(batch, EventBatch) and batch.lengths.tolist() == [2, 4]

    def test_all_windows_empty(self):
        batch = collate_events([_sample(0, 0), _sample(0, 1)])
        assert batch["events"].xy.shape == (2, 0, 2) and batch["labels"].shape == (2, 0)

    def test_other_keys_use_default_collate(self):
        batch = collate_events([_sample(1, 0, weight=0.5), _sample(2, 1, weight=2.0)])
        assert torch.equal(batch["weight"], torch.tensor([0.5, 2.0], dtype=torch.float64))

    def test_unlabelled_items(self):
        samples = [{"events": _window(2), "index": 0}, {"events": _window(1), "index": 1}]
        assert set(collate_events(samples)) == {"events", "index"}


class TestErrors:
    def test_no_samples(self):
        with pytest.raises(EventFormatError, match="at least one sample"):
            collate_events([])

    def test_mixed_sensor_sizes(self):
        with pytest.raises(EventFormatError, match=r"one sensor size \(H, W\)"):
            collate_events([_sample(2, 0), _sample(2, 1, sensor_size=(180, 240))])

    def test_mixed_keys(self):
        unlabelled = {key: value for key, value in _sample(2, 1).items() if key != "labels"}
        with pytest.raises(EventFormatError, match="sample 1 has keys"):
            collate_events([_sample(2, 0), unlabelled])

    def test_mixed_kinds(self):
        with pytest.raises(EventFormatError, match="must all be dicts or all EventBatch"):
            collate_events([_sample(2, 0), _window(2)])

    def test_no_events(self):
        with pytest.raises(EventFormatError, match="must hold 'events'"):
            collate_events([{"index": 0}])

    def test_labels_of_the_wrong_length(self):
        sample = _sample(3) | {"labels": torch.arange(2)}
        with pytest.raises(ShapeError, match=r"sample 0: 'labels' must hold one value per event, \(3,\)"):
            collate_events([sample])


class TestDataLoader:
    def test_workers_give_the_same_batches(self, labelled_dataset):
        def batches(workers):
            loader = DataLoader(
                labelled_dataset, batch_size=4, num_workers=workers, collate_fn=collate_events
            )
            return list(loader)

        serial, parallel = batches(0), batches(2)
        assert len(serial) == len(parallel) == -(-len(labelled_dataset) // 4)
        for one, two in zip(serial, parallel, strict=True):
            assert (
                one.keys()
                == two.keys()
                == {"events", "labels", "ignore", "t_start_us", "index", "sensor_size"}
            )
            for field, other in zip(one["events"], two["events"], strict=True):
                assert torch.equal(field, other)
            for key in ("labels", "ignore", "t_start_us", "index"):
                assert torch.equal(one[key], two[key])
            assert one["sensor_size"] == two["sensor_size"] == (90, 120)

    def test_batches_hold_the_items(self, labelled_dataset):
        loader = DataLoader(labelled_dataset, batch_size=3, collate_fn=collate_events)
        batch = next(iter(loader))
        for row in range(3):
            item = labelled_dataset[row]
            count = int(batch["events"].lengths[row])
            assert count == len(item["events"])
            assert torch.equal(batch["events"].xy[row, :count], item["events"].xy)
            assert torch.equal(batch["labels"][row, :count], item["labels"])
            assert (batch["labels"][row, count:] == -1).all() and batch["ignore"][row, count:].all()
