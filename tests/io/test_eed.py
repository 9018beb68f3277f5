import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.io import load_eed_boxes, load_frame_list


class TestBoxes:
    def test_parse(self, tmp_path):
        path = tmp_path / "boundingbox.txt"
        path.write_text(
            "1519689694.996659517, x= 2, y= 36, w= 24, h= 22\n\n"
            "# comment\n1519689695.016677141, x=3, y= 38, w= 29.5, h= 27  \n"
        )
        times, boxes = load_eed_boxes(path)
        np.testing.assert_array_equal(times, [1519689694.996659517, 1519689695.016677141])
        np.testing.assert_array_equal(boxes, [[2, 36, 24, 22], [3, 38, 29.5, 27]])
        assert times.dtype == boxes.dtype == np.float64

    @pytest.mark.parametrize(
        "bad", ["0.5, x= 1, y= 2, w= 3\n", "0.5 x= 1 y= 2 w= 3 h= 4\n", "0.5, x= one, y= 2, w= 3, h= 4\n"]
    )
    def test_bad_line_is_named(self, tmp_path, bad):
        path = tmp_path / "boundingbox.txt"
        path.write_text("0.1, x= 1, y= 2, w= 3, h= 4\n" + bad)
        with pytest.raises(
            ReaderError, match=r"boundingbox\.txt: line 2: expected 't, x= X, y= Y, w= W, h= H'"
        ):
            load_eed_boxes(path)

    def test_empty(self, tmp_path):
        path = tmp_path / "boundingbox.txt"
        path.write_text("\n")
        with pytest.raises(ReaderError, match="no bounding boxes"):
            load_eed_boxes(path)

    def test_missing(self, tmp_path):
        with pytest.raises(ReaderError, match="no such file"):
            load_eed_boxes(tmp_path / "boundingbox.txt")


class TestFrameList:
    def test_parse(self, tmp_path):
        path = tmp_path / "images.txt"
        path.write_text("1519689694.773328193 images/frame_00000000.png\n0.5   images/a b.png\n")
        times, files = load_frame_list(path)
        np.testing.assert_array_equal(times, [1519689694.773328193, 0.5])
        assert files == ["images/frame_00000000.png", "images/a b.png"]

    @pytest.mark.parametrize("bad", ["images/frame.png\n", "0.5\n", "t0 images/frame.png\n"])
    def test_bad_line_is_named(self, tmp_path, bad):
        path = tmp_path / "images.txt"
        path.write_text("0.1 images/x.png\n" + bad)
        with pytest.raises(ReaderError, match=r"images\.txt: line 2: expected 'time path'"):
            load_frame_list(path)

    def test_empty(self, tmp_path):
        path = tmp_path / "images.txt"
        path.write_text("# nothing\n")
        with pytest.raises(ReaderError, match="no frames"):
            load_frame_list(path)
