import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size, read_time_span


def _write(tmp_path, text):
    path = tmp_path / "events.txt"
    path.write_text(text)
    return path


class TestTextReader:
    def test_absolute_seconds_keep_microseconds(self, tmp_path):
        path = _write(tmp_path, "1519689694.766017193 129 100 1\n1519689694.766018193 176 0 0\n")
        events = load_events(path)
        assert events["t"].tolist() == [1519689694766017, 1519689694766018]
        assert events["x"].tolist() == [129, 176]
        assert events["y"].tolist() == [100, 0]
        assert events["p"].tolist() == [1, -1]

    def test_comments_blank_lines_and_signed_polarity(self, tmp_path):
        path = _write(tmp_path, "# header\n\n0.000001 1 2 1  # trailing comment\n   \n0.000002 3 4 -1\n")
        events = load_events(path)
        assert events["t"].tolist() == [1, 2]
        assert events["p"].tolist() == [1, -1]

    def test_time_span_of_a_short_file_keeps_its_first_line(self, tmp_path):
        # A file shorter than the tail read at its end: its first line is whole and may be the last event.
        assert read_time_span(_write(tmp_path, "0.000005 1 2 1\n0.000009 3 4 0\n")) == (5, 9)
        assert read_time_span(_write(tmp_path, "0.000005 1 2 1\n")) == (5, 5)

    def test_no_sensor_size(self, tmp_path):
        assert read_sensor_size(_write(tmp_path, "0 1 2 1\n")) is None

    @pytest.mark.parametrize(
        ("bad_line", "message"),
        [
            ("0.3 5 6\n", r"line 5: expected 4 values 't x y p', found 3: '0.3 5 6'"),
            ("0.3 5 6 1 9\n", "line 5: expected 4 values 't x y p', found 5"),
            ("0.3 5 six 1\n", "line 5: not a number in '0.3 5 six 1'"),
        ],
    )
    def test_malformed_line_is_named(self, tmp_path, bad_line, message):
        path = _write(tmp_path, "# c\n0.1 1 2 1\n\n0.2 3 4 0\n" + bad_line + "0.4 7 8 1\n")
        with pytest.raises(ReaderError, match=message) as info:
            load_events(path)
        assert str(info.value).startswith(str(path))
        with pytest.raises(ReaderError, match=message):
            list(iter_event_chunks(path, 2))

    def test_every_line_with_five_columns(self, tmp_path):
        path = _write(tmp_path, "0.1 1 2 1 7\n0.2 3 4 0 7\n")
        with pytest.raises(ReaderError, match="line 1: expected 4 values"):
            load_events(path)

    def test_line_numbers_count_from_the_file_start_in_later_chunks(self, tmp_path):
        lines = [f"0.{i:03d} 1 2 1\n" for i in range(1, 30)]
        lines[22] = "0.023 1 2\n"
        path = _write(tmp_path, "".join(lines))
        chunks = iter_event_chunks(path, 10)
        assert len(next(chunks)) == 10
        assert len(next(chunks)) == 10
        with pytest.raises(ReaderError, match="line 23: expected 4 values"):
            next(chunks)

    def test_comment_only_block_is_skipped(self, tmp_path):
        path = _write(tmp_path, "0.1 1 2 1\n# a\n# b\n0.2 3 4 0\n")
        chunks = list(iter_event_chunks(path, 1))
        assert [len(chunk) for chunk in chunks] == [1, 1]
        np.testing.assert_array_equal(np.concatenate(chunks), load_events(path))

    def test_binary_garbage(self, tmp_path):
        path = tmp_path / "events.txt"
        path.write_bytes(b"\x00\xff\x13 \x80\x81 1 2\n")
        with pytest.raises(ReaderError, match="line 1"):
            load_events(path)
