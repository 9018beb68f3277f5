"""The readers on the shared real recordings (skipped where they are absent)."""

import numpy as np
import pytest

from evseg_torch.io import iter_event_chunks, load_eed_boxes, load_events, load_frame_list, read_sensor_size

pytestmark = pytest.mark.realdata


def _assert_text_matches_npz(folder):
    text, npz = load_events(folder / "events.txt"), load_events(folder / "events.npz")
    assert len(text) == len(npz)
    np.testing.assert_array_equal(text["t"] - text["t"][0], npz["t"] - npz["t"][0])
    np.testing.assert_array_equal(text[["x", "y", "p"]], npz[["x", "y", "p"]])
    return text, npz


class TestEed:
    def test_occlusions_text_and_npz_agree(self, real_data):
        folder = real_data / "eed_occlusions"
        text, _ = _assert_text_matches_npz(folder)
        assert len(text) == 116604
        assert text["t"][0] == 1519689694766017  # t0 = 1519689694.766017193 s
        with np.load(folder / "events.npz") as raw:
            exact_us = (int(raw["t0_ns"]) + raw["t_ns_rel"]) // 1000
        np.testing.assert_array_equal(text["t"], exact_us)
        assert (text["t"][-1] - text["t"][0]) / 1e6 == pytest.approx(0.660, abs=1e-3)
        assert read_sensor_size(folder / "events.npz") == (180, 240)
        assert text["x"].max() < 240 and text["y"].max() < 180

    def test_occlusions_boxes_and_frames(self, real_data):
        folder = real_data / "eed_occlusions"
        times, boxes = load_eed_boxes(folder / "boundingbox.txt")
        events = load_events(folder / "events.txt")
        assert boxes.shape == (13, 4)
        offsets = times - events["t"][0] / 1e6
        assert offsets[0] == pytest.approx(0.23, abs=0.01) and offsets[-1] == pytest.approx(0.47, abs=0.01)
        assert np.all(boxes[:, 2:] > 0) and np.all(boxes[:, 0] + boxes[:, 2] <= 240)
        frame_times, files = load_frame_list(folder / "images.txt")
        assert len(files) == 15 and all((folder / name).is_file() for name in files)
        assert np.all(np.diff(frame_times) > 0)

    def test_what_is_background(self, real_data):
        folder = real_data / "eed_what_is_background"
        text, _ = _assert_text_matches_npz(folder)
        assert len(text) == 271264 and text["t"][0] == 0
        assert read_sensor_size(folder / "events.npz") == (180, 190)
        times, boxes = load_eed_boxes(folder / "boundingbox.txt")
        times_rel, boxes_rel = load_eed_boxes(folder / "boundingbox_rel.txt")
        assert boxes.shape == boxes_rel.shape == (14, 4)
        np.testing.assert_array_equal(boxes, boxes_rel)
        np.testing.assert_allclose(times_rel, times - times[0], atol=1e-6)
        # The relative boxes share the events' time base: both span 0.260 s from 0.
        assert times_rel[0] == 0 and times_rel[-1] == pytest.approx(text["t"][-1] / 1e6, abs=1e-3)
        frame_times, files = load_frame_list(folder / "images.txt")
        # The README counts 21 frames in images/, but images.txt lists 20 (frame_00000020.png is unlisted).
        assert len(files) == 20 and all((folder / name).is_file() for name in files)
        assert np.all(np.diff(frame_times) > 0) and frame_times[0] < times[0] < frame_times[-1]

    def test_chunks_of_a_real_text_file(self, real_data):
        path = real_data / "eed_occlusions" / "events.txt"
        chunks = list(iter_event_chunks(path, 50_000))
        assert [len(chunk) for chunk in chunks] == [50_000, 50_000, 16_604]
        np.testing.assert_array_equal(np.concatenate(chunks), load_events(path))


class TestEcd:
    def test_shapes_rotation_text_and_npz_agree(self, real_data):
        folder = real_data / "ecd_shapes_rotation_first120k"
        text, _ = _assert_text_matches_npz(folder)
        assert len(text) == 120000
        assert text[0].tolist() == (0, 33, 39, 1)
        assert text["t"][-1] == 1428658
        assert read_sensor_size(folder / "events.npz") == (180, 240)

    @pytest.mark.parametrize(
        ("name", "count", "first_s", "last_s"),
        [("poster_translation.npz", 100000, 39.1268, 39.2001), ("poster_6dof.npz", 30000, 36.5674, 36.5715)],
    )
    def test_poster_pydvs(self, real_data, name, count, first_s, last_s):
        path = real_data / "ecd_poster_pydvs" / name
        events = load_events(path, sensor_size=(180, 240))
        assert len(events) == count
        assert events["t"][0] / 1e6 == pytest.approx(first_s, abs=1e-4)
        assert events["t"][-1] / 1e6 == pytest.approx(last_s, abs=1e-4)
        assert set(np.unique(events["p"])) == {-1, 1}
        assert read_sensor_size(path) is None


class TestOtherRecordings:
    def test_dvs128_aedat_matches_the_derived_npz(self, real_data):
        folder = real_data / "dvs128_person_walking"
        aedat = load_events(folder / "alex_walking_for_10secs.aedat")
        npz = load_events(folder / "events.npz")
        with np.load(folder / "events.npz") as raw:
            t0 = int(raw["t0_us_raw"])
        assert len(aedat) == 125028
        np.testing.assert_array_equal(aedat["t"] - t0, npz["t"])
        np.testing.assert_array_equal(aedat[["x", "y", "p"]], npz[["x", "y", "p"]])
        assert read_sensor_size(folder / "alex_walking_for_10secs.aedat") == (128, 128)

    def test_prophesee_structured_npy(self, real_data):
        path = real_data / "prophesee_gen4_driving_expelliarmus" / "evt3_sample.npy"
        events = load_events(path, sensor_size=(720, 1280))
        assert len(events) == 219596 and events["t"][0] == 11718656
        assert np.ptp(events["t"]) == pytest.approx(53_900, abs=100)

    def test_celex_without_polarity(self, real_data):
        path = real_data / "celex_two_hands_evmotionseg" / "events.npz"
        events = load_events(path)
        assert len(events) == 473194 and np.all(events["p"] == 1)
        assert events["t"][0] == 8131092 and events["t"][-1] == 11160616
        assert read_sensor_size(path) == (800, 1280)
