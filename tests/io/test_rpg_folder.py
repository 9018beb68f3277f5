"""rpg / ECD / EED sequence folders: ``events.txt`` read as the text file, the sensor size from the frames."""

import cv2
import numpy as np
import pytest

from evseg_torch.errors import EventFormatError, ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size, read_time_span, reader_for
from tests.helpers.io import HEIGHT, WIDTH, make_events, write_txt


def write_sequence(folder, events, frame_shape=(HEIGHT, WIDTH)):
    """The layout: events.txt, images.txt listing frames under images/."""
    (folder / "images").mkdir(parents=True)
    write_txt(folder / "events.txt", events)
    if frame_shape is not None:
        for index in range(2):
            cv2.imwrite(str(folder / "images" / f"frame_{index:08d}.png"), np.zeros(frame_shape, np.uint8))
        (folder / "images.txt").write_text(
            "".join(f"{index * 0.05:.6f} images/frame_{index:08d}.png\n" for index in range(2))
        )
    return folder


class TestRpgFolder:
    def test_events_are_the_text_files(self, tmp_path):
        events = make_events()
        folder = write_sequence(tmp_path / "seq", events)
        assert reader_for(folder) == "rpg / ECD / EED sequence folder"
        read = load_events(folder)
        np.testing.assert_array_equal(read, load_events(folder / "events.txt"))
        np.testing.assert_array_equal(read, events)
        np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(folder, 128))), read)
        assert read_time_span(folder) == (int(events["t"][0]), int(events["t"][-1]))

    def test_sensor_size_is_the_first_frames(self, tmp_path):
        # Larger than the events need: the frames, not the events, give a DAVIS's size.
        folder = write_sequence(tmp_path / "seq", make_events(), frame_shape=(HEIGHT + 60, WIDTH + 112))
        assert read_sensor_size(folder) == (HEIGHT + 60, WIDTH + 112)
        assert load_events(folder).shape == (500,)

    def test_without_frames_no_sensor_size(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", make_events(), frame_shape=None)
        assert read_sensor_size(folder) is None

    def test_unreadable_first_frame_is_named(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", make_events())
        (folder / "images" / "frame_00000000.png").write_bytes(b"not a png")
        with pytest.raises(ReaderError, match=r"lists 'images/frame_00000000\.png' first, which is not a"):
            read_sensor_size(folder)

    def test_frames_smaller_than_the_events_are_an_error(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", make_events(), frame_shape=(HEIGHT // 2, WIDTH))
        with pytest.raises(EventFormatError, match=r"seq: y = \d+ lies outside the sensor \(H = 60\)"):
            load_events(folder)
