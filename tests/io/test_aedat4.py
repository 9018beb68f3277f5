"""The AEDAT 4 reader, on a stand-in decoder: no AEDAT 4 sample is at hand and none can be written here."""

import itertools
from typing import ClassVar

import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import aedat4, iter_event_chunks, load_events, read_sensor_size
from tests.helpers.io import make_events

AEDAT_DTYPE = np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), (("p", "on"), "?")])


def _packet(events):
    out = np.empty(len(events), dtype=AEDAT_DTYPE)
    out["t"], out["x"], out["y"], out["on"] = events["t"], events["x"], events["y"], events["p"] > 0
    return out


class FakeDecoder:
    """Packets of the event stream 1 interleaved with frames (stream 0) and a second event stream (2)."""

    source = make_events(250)
    streams: ClassVar[dict] = {
        0: {"type": "frame", "width": 346, "height": 260},
        1: {"type": "events", "width": 346, "height": 260},
        2: {"type": "events", "width": 10, "height": 10},
    }

    def __init__(self, path):
        self.path = path
        bounds = [0, 3, 40, 41, 130, 250]
        packets = [
            {"stream_id": 1, "events": _packet(self.source[a:b])} for a, b in itertools.pairwise(bounds)
        ]
        frame = {"stream_id": 0, "frame": {"width": 346, "height": 260}}
        other = {"stream_id": 2, "events": _packet(make_events(5, seed=1))}
        self._packets = iter([frame, packets[0], other, *packets[1:3], frame, *packets[3:]])

    def id_to_stream(self):
        return self.streams

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._packets)


@pytest.fixture
def fake_file(tmp_path, monkeypatch):
    monkeypatch.setattr(aedat4.aedat, "Decoder", FakeDecoder)
    path = tmp_path / "recording.aedat4"
    path.write_bytes(b"")
    return path


class TestAedat4Reader:
    def test_first_event_stream(self, fake_file):
        np.testing.assert_array_equal(load_events(fake_file), FakeDecoder.source)
        assert read_sensor_size(fake_file) == (260, 346)

    @pytest.mark.parametrize("chunk_size", [1, 2, 37, 100, 250, 1000])
    def test_chunks_regroup_packets(self, fake_file, chunk_size):
        chunks = list(iter_event_chunks(fake_file, chunk_size))
        sizes = [len(chunk) for chunk in chunks]
        assert sizes[:-1] == [chunk_size] * (len(sizes) - 1) and 0 < sizes[-1] <= chunk_size
        np.testing.assert_array_equal(np.concatenate(chunks), FakeDecoder.source)

    def test_no_event_stream(self, fake_file, monkeypatch):
        monkeypatch.setattr(FakeDecoder, "streams", {0: {"type": "imus"}})
        with pytest.raises(ReaderError, match=r"recording\.aedat4: the file holds no event stream"):
            load_events(fake_file)

    def test_real_decoder_on_a_corrupt_file(self, tmp_path):
        path = tmp_path / "recording.aedat4"
        path.write_bytes(b"#!AER-DAT4.0\r\n" + bytes(range(256)) * 4)
        with pytest.raises(ReaderError, match=r"recording\.aedat4: cannot read AEDAT 4 file"):
            load_events(path)
