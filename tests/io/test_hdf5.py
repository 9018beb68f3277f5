import h5py
import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size
from tests.helpers.io import T0_US, make_events, write_h5_dsec, write_h5_event_utils


class TestHdf5Reader:
    def test_dsec_time_is_shifted_by_t_offset(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_dsec(path, events, t_offset=T0_US - 5)
        with h5py.File(path, "r") as file:
            assert int(file["events/t"][0]) == events["t"][0] - T0_US + 5
        np.testing.assert_array_equal(load_events(path), events)

    def test_dsec_without_t_offset(self, tmp_path):
        events = make_events(t0_us=1000)
        path = tmp_path / "events.h5"
        write_h5_dsec(path, events, t_offset=0)
        with h5py.File(path, "a") as file:
            del file["t_offset"]
        np.testing.assert_array_equal(load_events(path), events)

    def test_event_utils_integer_polarity(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_event_utils(path, events)
        with h5py.File(path, "a") as file:
            del file["events/ps"]
            file["events/ps"] = np.where(events["p"] > 0, 1, 0).astype(np.int8)
        np.testing.assert_array_equal(load_events(path), events)

    def test_no_sensor_resolution(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_event_utils(path, events)
        with h5py.File(path, "a") as file:
            del file.attrs["sensor_resolution"]
        assert read_sensor_size(path) is None

    def test_no_events_group(self, tmp_path):
        path = tmp_path / "events.h5"
        with h5py.File(path, "w") as file:
            file["images/image000"] = np.zeros((2, 2))
        with pytest.raises(ReaderError, match=r"events\.h5: no 'events' group; expected datasets"):
            load_events(path)
        with pytest.raises(ReaderError, match="no 'events' group"):
            list(iter_event_chunks(path))

    def test_events_group_of_unknown_layout(self, tmp_path):
        path = tmp_path / "events.h5"
        with h5py.File(path, "w") as file:
            file["events/xs"] = np.zeros(3)
            file["events/t"] = np.zeros(3)
        with pytest.raises(ReaderError, match=r"holds \['t', 'xs'\]"):
            load_events(path)

    def test_datasets_of_different_lengths(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_event_utils(path, events)
        with h5py.File(path, "a") as file:
            del file["events/ys"]
            file["events/ys"] = np.zeros(3, dtype=np.int16)
        with pytest.raises(ReaderError, match="1-D and of one length"):
            load_events(path)

    def test_integer_seconds_are_refused(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_event_utils(path, events)
        with h5py.File(path, "a") as file:
            del file["events/ts"]
            file["events/ts"] = events["t"]
        with pytest.raises(ReaderError, match="events/ts must hold float seconds"):
            load_events(path)

    def test_not_hdf5(self, tmp_path):
        path = tmp_path / "events.hdf5"
        path.write_bytes(b"garbage" * 100)
        with pytest.raises(ReaderError, match=r"events\.hdf5: cannot read HDF5 events file"):
            load_events(path)

    def test_truncated(self, tmp_path, events):
        path = tmp_path / "events.h5"
        write_h5_event_utils(path, events)
        path.write_bytes(path.read_bytes()[:3000])
        with pytest.raises(ReaderError, match=r"events\.h5: cannot read HDF5 events file") as info:
            load_events(path)
        assert "\n" not in str(info.value)

    def test_blosc_compressed_dsec(self, tmp_path, events):
        hdf5plugin = pytest.importorskip("hdf5plugin")
        path = tmp_path / "events.h5"
        with h5py.File(path, "w") as file:
            for name, column in [("x", events["x"]), ("y", events["y"]), ("p", events["p"] > 0)]:
                file.create_dataset(f"events/{name}", data=column.astype(np.uint16), **hdf5plugin.Blosc())
            file.create_dataset(
                "events/t", data=(events["t"] - T0_US).astype(np.uint32), **hdf5plugin.Blosc()
            )
            file.create_dataset("t_offset", data=np.int64(T0_US))
        np.testing.assert_array_equal(load_events(path), events)
