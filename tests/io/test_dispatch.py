import subprocess
import sys

import numpy as np
import pytest

from evseg_torch.errors import ConfigError, EventFormatError, ReaderError
from evseg_torch.events import EVENT_DTYPE
from evseg_torch.io import (
    SUPPORTED_SUFFIXES,
    iter_event_chunks,
    load_events,
    read_sensor_size,
    read_time_span,
)
from tests.helpers.io import HEIGHT, WIDTH, make_events, write_npz_columns, write_txt


class TestRoundTrip:
    def test_load_equals_source(self, written):
        path, source, _ = written
        events = load_events(path)
        assert events.dtype == EVENT_DTYPE
        np.testing.assert_array_equal(events, source)

    def test_read_sensor_size(self, written):
        path, _, size = written
        assert read_sensor_size(path) == size

    def test_result_is_an_owned_writable_copy(self, written):
        path, source, _ = written
        events = load_events(path)
        assert events.flags.writeable and events.flags.owndata
        events["x"] = 0
        np.testing.assert_array_equal(load_events(path), source)

    def test_read_time_span(self, written):
        path, source, _ = written
        assert read_time_span(path) == (int(source["t"][0]), int(source["t"][-1]))

    def test_str_path(self, written):
        path, source, _ = written
        np.testing.assert_array_equal(load_events(str(path)), source)


def test_time_span_is_none_where_not_cheap_or_unreadable(tmp_path):
    """Progress bars then go without a total: formats read only by a pass, missing or broken files."""
    (tmp_path / "events.aedat").write_bytes(b"#!AER-DAT2.0\r\n")
    (tmp_path / "broken.npy").write_bytes(b"not an array")
    (tmp_path / "comments.txt").write_text("# nothing but a comment\n")
    for name in ("events.aedat", "broken.npy", "comments.txt", "missing.npy", "events.unknown"):
        assert read_time_span(tmp_path / name) is None


class TestChunks:
    @pytest.mark.parametrize("chunk_size", [1, 7, 500, 10_000])
    def test_chunks_concatenate_to_full(self, written, chunk_size):
        path, source, _ = written
        chunks = list(iter_event_chunks(path, chunk_size))
        assert all(0 < len(chunk) <= chunk_size for chunk in chunks)
        assert all(chunk.dtype == EVENT_DTYPE for chunk in chunks)
        np.testing.assert_array_equal(np.concatenate(chunks), source)

    def test_full_chunks_except_the_last(self, written):
        path, source, _ = written
        sizes = [len(chunk) for chunk in iter_event_chunks(path, 64)]
        expected = [64] * (len(source) // 64) + [len(source) % 64]
        if path.suffix == ".txt":  # the header comment takes one line of the first block
            expected = [63] + [64] * ((len(source) - 63) // 64) + [(len(source) - 63) % 64]
        assert sizes == [size for size in expected if size]

    @pytest.mark.parametrize("chunk_size", [0, -3, 2.5, True, "10"])
    def test_bad_chunk_size(self, tmp_path, chunk_size):
        with pytest.raises(ConfigError, match="chunk_size must be an integer of at least 1"):
            iter_event_chunks(tmp_path / "events.txt", chunk_size)

    def test_decrease_across_a_chunk_boundary(self, tmp_path):
        events = make_events(20)
        events["t"][10:] -= 10_000  # the jump backwards sits exactly between chunks of 10
        path = tmp_path / "events.npz"
        write_npz_columns(path, events)
        chunks = iter_event_chunks(path, 10)
        next(chunks)
        with pytest.raises(EventFormatError, match=r"events\.npz: timestamps decrease at event 10"):
            next(chunks)

    def test_decrease_inside_a_chunk_names_the_chunk(self, tmp_path):
        events = make_events(20)
        events["t"][15:] -= 10_000
        path = tmp_path / "events.txt"
        write_txt(path, events)
        with pytest.raises(EventFormatError, match=r"events\.txt: in the chunk starting at event 9"):
            list(iter_event_chunks(path, 10))

    def test_missing_file_raises_at_once(self, tmp_path):
        with pytest.raises(ReaderError, match="no such file"):
            iter_event_chunks(tmp_path / "absent.h5")

    def test_empty_file(self, tmp_path):
        path = tmp_path / "events.txt"
        path.write_text("# only a comment\n")
        with pytest.raises(EventFormatError, match="0 events"):
            list(iter_event_chunks(path))


class TestErrors:
    def test_missing_file(self, tmp_path):
        with pytest.raises(ReaderError, match=r"absent\.txt: no such file"):
            load_events(tmp_path / "absent.txt")

    def test_folder_of_no_known_layout(self, tmp_path):
        folder = tmp_path / "folder.npz"
        folder.mkdir()
        with pytest.raises(ReaderError, match="folder of no known layout; supported folders: EVIMO2v2"):
            load_events(folder)

    @pytest.mark.parametrize("name", ["events.csv", "events", "events.mcap"])
    def test_unknown_suffix(self, tmp_path, name):
        path = tmp_path / name
        path.write_text("0 1 2 1\n")
        with pytest.raises(ReaderError, match="unknown event file suffix") as info:
            load_events(path)
        assert all(suffix in str(info.value) for suffix in SUPPORTED_SUFFIXES)
        with pytest.raises(ReaderError, match="unknown event file suffix"):
            read_sensor_size(path)

    def test_suffix_case_is_ignored(self, tmp_path, events):
        path = tmp_path / "EVENTS.TXT"
        write_txt(path, events)
        np.testing.assert_array_equal(load_events(path), events)

    def test_decreasing_time_names_the_file(self, tmp_path):
        events = make_events(30)
        events["t"][20:] -= 10_000
        path = tmp_path / "events.txt"
        write_txt(path, events)
        with pytest.raises(EventFormatError, match=r"events\.txt: timestamps decrease at event 20"):
            load_events(path)

    def test_outside_the_given_sensor(self, tmp_path, events):
        path = tmp_path / "events.txt"
        write_txt(path, events)
        with pytest.raises(EventFormatError, match=r"events\.txt: x = \d+ lies outside the sensor"):
            load_events(path, sensor_size=(HEIGHT, 10))
        np.testing.assert_array_equal(load_events(path, sensor_size=(HEIGHT, WIDTH)), events)

    def test_outside_the_stored_sensor(self, tmp_path, events):
        path = tmp_path / "events.npz"
        write_npz_columns(path, events)
        np.savez(path, **{**dict(np.load(path)), "width": np.int32(10)})
        with pytest.raises(EventFormatError, match="outside the sensor"):
            load_events(path)
        with pytest.raises(EventFormatError, match="outside the sensor"):
            list(iter_event_chunks(path, 100))
        assert len(load_events(path, sensor_size=(HEIGHT, WIDTH))) == len(events)


_WITHOUT_OPTIONAL_PACKAGES = """
import importlib.abc, sys
OPTIONAL = {"aedat", "rosbags", "h5py", "hdf5plugin", "expelliarmus", "av", "matplotlib", "tonic", "dask"}
class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in OPTIONAL:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Absent())
"""


def test_import_needs_no_optional_package_and_a_reader_that_does_says_which(tmp_path):
    """``import evseg_torch`` needs no optional package; a reader that needs one says so in one line."""
    recording = tmp_path / "recording.aedat4"
    recording.write_bytes(b"not read")
    events = tmp_path / "events.txt"
    write_txt(events, make_events(50))
    script = _WITHOUT_OPTIONAL_PACKAGES + (
        "from evseg_torch import CascadedSegmenter\n"
        "from evseg_torch.errors import ReaderError\n"
        "from evseg_torch.io import load_events\n"
        f"print(len(load_events({str(events)!r})))\n"
        "try:\n"
        f"    load_events({str(recording)!r})\n"
        "except ReaderError as err:\n"
        "    print(err)\n"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    count, error = run.stdout.splitlines()
    assert count == "50"
    assert error == (
        f"{recording}: this AEDAT 4 file needs the optional package 'aedat' to be read: "
        "pip install 'evseg-torch[io]'"
    )
