import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size
from tests.helpers.io import aedat2_bytes, make_events


@pytest.fixture
def jaer_events():
    return make_events(300, t0_us=262_847_757)


class TestAedat2Reader:
    def test_round_trip(self, tmp_path, jaer_events):
        path = tmp_path / "walk.aedat"
        path.write_bytes(aedat2_bytes(jaer_events))
        np.testing.assert_array_equal(load_events(path), jaer_events)
        assert read_sensor_size(path) == (128, 128)
        np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(path, 64))), jaer_events)

    def test_special_events_are_dropped(self, tmp_path, jaer_events):
        raw = bytearray(aedat2_bytes(jaer_events))
        body = len(raw) - 8 * len(jaer_events)
        raw[body + 8 * 10 + 2] |= 0x80  # bit 15 of the 11th address: an external event
        path = tmp_path / "walk.aedat"
        path.write_bytes(bytes(raw))
        np.testing.assert_array_equal(load_events(path), np.delete(jaer_events, 10))

    def test_truncated(self, tmp_path, jaer_events):
        path = tmp_path / "walk.aedat"
        path.write_bytes(aedat2_bytes(jaer_events)[:-3])
        with pytest.raises(ReaderError, match=r"walk\.aedat: truncated: \d+ bytes after the header"):
            load_events(path)

    def test_other_chip(self, tmp_path, jaer_events):
        path = tmp_path / "davis.aedat"
        path.write_bytes(aedat2_bytes(jaer_events, chip=b"eu.seebetter.ini.chips.davis.DAVIS240C"))
        with pytest.raises(
            ReaderError, match=r"AEChip 'eu\.seebetter.ini.chips.davis.DAVIS240C' is not supported"
        ):
            load_events(path)

    def test_other_version(self, tmp_path, jaer_events):
        path = tmp_path / "v3.aedat"
        path.write_bytes(aedat2_bytes(jaer_events, version=b"#!AER-DAT3.1"))
        with pytest.raises(ReaderError, match=r"not a jAER AEDAT 2\.0 file"):
            read_sensor_size(path)
