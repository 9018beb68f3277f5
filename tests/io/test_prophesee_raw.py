"""The Prophesee RAW / DAT reader: files from the decoder's own encoder, headers, and the shared samples."""

import json

import numpy as np
import pytest
from expelliarmus import Wizard

from evseg_torch.app.cli import main
from evseg_torch.errors import ReaderError
from evseg_torch.events import as_events
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size, reader_for
from tests.helpers.io import make_events

SAMPLES = "prophesee_gen4_driving_expelliarmus"


def _write(path, events, encoding):
    """Encode canonical events with expelliarmus, which writes its own header (a Gen3 or Gen4.1 plugin)."""
    data = np.zeros(len(events), dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    data["t"], data["x"], data["y"], data["p"] = events["t"], events["x"], events["y"], events["p"] > 0
    Wizard(encoding=encoding).save(path, data)
    return path


def _with_header(path, header: bytes, body_of):
    """A file of ``header`` followed by the binary body of the file ``body_of`` (its header dropped)."""
    data = body_of.read_bytes()
    start = 0
    while data.startswith(b"%", start):
        start = data.index(b"\n", start) + 1
    path.write_bytes(header + data[start:])
    return path


@pytest.fixture
def events():
    return make_events(n=3000, t0_us=1_000_000)


@pytest.mark.parametrize(
    ("name", "encoding", "size"),
    [("a.raw", "evt2", (480, 640)), ("a.raw", "evt3", (720, 1280)), ("a.dat", "dat", None)],
)
def test_round_trip(tmp_path, events, name, encoding, size):
    path = _write(tmp_path / name, events, encoding)
    np.testing.assert_array_equal(load_events(path), events)
    assert read_sensor_size(path) == size  # the camera plugin in the header; none in the DAT header
    chunks = list(iter_event_chunks(path, chunk_size=700))
    assert [len(c) for c in chunks] == [700, 700, 700, 700, 200]
    np.testing.assert_array_equal(np.concatenate(chunks), events)
    assert reader_for(path) == "Prophesee RAW/DAT file"


@pytest.mark.parametrize(
    ("header", "size"),
    [
        (b"% evt 3.0\n% geometry 320x240\n% end\n", (240, 320)),
        (b"% format EVT3;height=260;width=346\n% end\n", (260, 346)),
        (b"% evt 3.0\n% plugin_name hal_plugin_someone_else\n", None),
    ],
)
def test_sensor_size_from_header(tmp_path, events, header, size):
    body = _write(tmp_path / "body.raw", events, "evt3")
    path = _with_header(tmp_path / "a.raw", header, body)
    assert read_sensor_size(path) == size
    np.testing.assert_array_equal(load_events(path), events)


def test_header_cut_mid_line_is_refused_not_decoded(tmp_path, events):
    # The decoder loops forever on such a file; the header is checked before it runs.
    path = tmp_path / "cut.raw"
    path.write_bytes(_write(tmp_path / "a.raw", events, "evt3").read_bytes()[:60])
    with pytest.raises(ReaderError, match=r"cut\.raw: .*ends inside its text header"):
        load_events(path)


def test_header_without_events(tmp_path):
    path = tmp_path / "empty.raw"
    path.write_bytes(b"% evt 3.0\n% end\n")
    with pytest.raises(ReaderError, match="a header and no event data"):
        load_events(path)


def test_unknown_encoding(tmp_path, events):
    body = _write(tmp_path / "body.raw", events, "evt3")
    path = _with_header(tmp_path / "a.raw", b"% evt 2.1\n", body)
    with pytest.raises(ReaderError, match=r"no event encoding the decoder reads .*'2\.1'"):
        load_events(path)


def test_corrupt_body(tmp_path):
    path = tmp_path / "noise.raw"
    path.write_bytes(b"% evt 3.0\n" + np.random.default_rng(0).bytes(1000))
    with pytest.raises(ReaderError, match=r"noise\.raw: .*empty or corrupt"):
        load_events(path)


@pytest.mark.realdata
def test_evt3_sample_equals_its_reference_decoding(real_data):
    folder = real_data / SAMPLES
    events = load_events(folder / "evt3_sample.raw")
    np.testing.assert_array_equal(events, as_events(np.load(folder / "evt3_sample.npy")))
    assert read_sensor_size(folder / "evt3_sample.raw") == (720, 1280)
    chunks = list(iter_event_chunks(folder / "evt3_sample.raw", chunk_size=50_000))
    assert max(len(c) for c in chunks) == 50_000
    np.testing.assert_array_equal(np.concatenate(chunks), events)


@pytest.mark.realdata
def test_evt2_sample_loads(real_data):
    path = real_data / SAMPLES / "evt2_sample.raw"
    events = load_events(path)
    assert len(events) == 539_481  # the decoder's count; the sample has no reference decoding
    assert read_sensor_size(path) == (480, 640)  # hal_plugin_gen3_fx3
    assert np.all(np.diff(events["t"]) >= 0) and set(np.unique(events["p"])) == {-1, 1}


@pytest.mark.realdata
def test_cli_segments_the_evt2_sample(real_data, tmp_path):
    path = real_data / SAMPLES / "evt2_sample.raw"
    assert main(["--quiet", "segment", str(path), "--out", str(tmp_path), "--window-ms", "25"]) == 0
    summary = json.loads((tmp_path / "evt2_sample" / "summary.json").read_text())
    assert summary["events"] == 539_481 and summary["windows"] == 2
    assert summary["sensor_size"] == [480, 640]
