import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size
from tests.helpers.io import as_seconds_array, write_npz_columns


class TestNpy:
    def test_integer_array(self, tmp_path, events):
        path = tmp_path / "events.npy"
        data = np.column_stack([np.arange(5), np.arange(5), np.arange(5), np.ones(5)]).astype(np.int32)
        np.save(path, data)
        assert load_events(path)["t"].tolist() == [0, 1_000_000, 2_000_000, 3_000_000, 4_000_000]

    @pytest.mark.parametrize("shape", [(10, 3), (10,), (2, 5, 4)])
    def test_wrong_shape(self, tmp_path, shape):
        path = tmp_path / "events.npy"
        np.save(path, np.zeros(shape))
        with pytest.raises(ReaderError, match=r"expected \(N, 4\)"):
            load_events(path)

    def test_pickled_content_is_refused(self, tmp_path):
        path = tmp_path / "events.npy"
        np.save(path, np.array([{"t": 1}], dtype=object), allow_pickle=True)
        with pytest.raises(ReaderError, match=r"events\.npy: cannot read NumPy \.npy events file"):
            load_events(path)

    def test_truncated(self, tmp_path, events):
        path = tmp_path / "events.npy"
        np.save(path, as_seconds_array(events))
        path.write_bytes(path.read_bytes()[:-100])
        with pytest.raises(ReaderError, match=r"events\.npy: cannot read"):
            load_events(path)

    def test_not_an_npy(self, tmp_path):
        path = tmp_path / "events.npy"
        path.write_text("0 1 2 1\n")
        with pytest.raises(ReaderError, match="cannot read"):
            load_events(path)


class TestNpz:
    def test_truncated(self, tmp_path, events):
        path = tmp_path / "events.npz"
        write_npz_columns(path, events)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        with pytest.raises(ReaderError, match=r"events\.npz: cannot read NumPy \.npz events file"):
            load_events(path)
        with pytest.raises(ReaderError, match="cannot read"):
            read_sensor_size(path)

    def test_corrupt_member(self, tmp_path, events):
        path = tmp_path / "events.npz"
        np.savez_compressed(path, events=as_seconds_array(events))
        raw = bytearray(path.read_bytes())
        raw[200:260] = bytes(60)  # inside the compressed member
        path.write_bytes(bytes(raw))
        with pytest.raises(ReaderError, match="cannot read"):
            load_events(path)

    def test_unknown_layout_lists_keys(self, tmp_path):
        path = tmp_path / "events.npz"
        np.savez(path, ts=np.zeros(3), xs=np.zeros(3))
        with pytest.raises(ReaderError, match=r"unknown npz layout with keys \['ts', 'xs'\]"):
            load_events(path)

    def test_single_unnamed_array(self, tmp_path, events):
        path = tmp_path / "events.npz"
        np.savez(path, as_seconds_array(events))
        np.testing.assert_array_equal(load_events(path), events)

    def test_events_of_wrong_shape(self, tmp_path):
        path = tmp_path / "events.npz"
        np.savez(path, events=np.zeros((4, 3)))
        with pytest.raises(ReaderError, match=r"'events' has shape \(4, 3\)"):
            load_events(path)

    def test_columns_of_different_lengths(self, tmp_path):
        path = tmp_path / "events.npz"
        np.savez(path, t_us=np.arange(3), x=np.zeros(3), y=np.zeros(2), p=np.zeros(3))
        with pytest.raises(ReaderError, match="of one length"):
            load_events(path)

    def test_float_microseconds_are_refused(self, tmp_path):
        path = tmp_path / "events.npz"
        np.savez(path, t_us=np.arange(3.0), x=np.zeros(3), y=np.zeros(3), p=np.zeros(3))
        with pytest.raises(ReaderError, match="microsecond timestamps must be integers"):
            load_events(path)

    def test_celex_layout_has_positive_polarity(self, tmp_path, events):
        path = tmp_path / "events.npz"
        np.savez(
            path,
            t_raw=events["t"],
            x=events["x"].astype(np.uint16),
            y=events["y"].astype(np.uint16),
            width=np.int32(1280),
            height=np.int32(800),
        )
        loaded = load_events(path)
        assert np.all(loaded["p"] == 1)
        np.testing.assert_array_equal(loaded[["t", "x", "y"]], events[["t", "x", "y"]])
        assert read_sensor_size(path) == (800, 1280)

    def test_pickled_member_is_never_loaded(self, tmp_path, events):
        path = tmp_path / "events.npz"
        np.savez(path, events=as_seconds_array(events), meta=np.array({"frames": []}, dtype=object))
        np.testing.assert_array_equal(load_events(path), events)
        assert len(np.concatenate(list(iter_event_chunks(path, 100)))) == len(events)
