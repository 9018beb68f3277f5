import numpy as np
import pytest

from evseg_torch.errors import EventFormatError, ReaderError, ShapeError
from evseg_torch.io import (
    EvimoSequence,
    iter_event_chunks,
    load_events,
    load_evimo,
    read_sensor_size,
    save_evimo,
)
from tests.helpers.io import HEIGHT, WIDTH, make_events


@pytest.fixture
def sequence():
    rng = np.random.default_rng(3)
    events = make_events(400, t0_us=2_000_000)
    masks = np.zeros((3, HEIGHT, WIDTH), dtype=np.int64)
    masks[:, 10:30, 20:50] = 1
    masks[1:, 60:80, 70:90] = 23
    masks[2, rng.integers(0, HEIGHT, 5), rng.integers(0, WIDTH, 5)] = 65
    times = np.array([2.0, 2.0035, 2.0071])
    K = np.array([[200.0, 0.0, 60.5], [0.0, 201.0, 59.0], [0.0, 0.0, 1.0]])
    D = np.array([-0.3, 0.1, 0.001, -0.002])
    return events, masks, times, K, D


@pytest.fixture
def saved(tmp_path, sequence):
    path = save_evimo(tmp_path / "seq.npz", *sequence[:3], K=sequence[3], D=sequence[4])
    return path, sequence


class TestEvimo:
    def test_round_trip(self, saved):
        path, (events, masks, times, K, D) = saved
        sequence = load_evimo(path, trusted=True)
        assert isinstance(sequence, EvimoSequence)
        np.testing.assert_array_equal(sequence.events, events)
        np.testing.assert_array_equal(sequence.masks, masks)
        np.testing.assert_array_equal(sequence.mask_times_s, times)
        np.testing.assert_array_equal(sequence.K, K)
        np.testing.assert_array_equal(sequence.D, D)
        assert sequence.sensor_size == (HEIGHT, WIDTH)

    def test_file_layout(self, saved):
        path, (events, masks, times, _, _) = saved
        with np.load(path, allow_pickle=True) as npz:
            assert npz["events"].shape == (len(events), 4)
            assert set(np.unique(npz["events"][:, 3])) <= {0.0, 1.0}
            np.testing.assert_array_equal(npz["mask"], masks * 1000)
            meta = npz["meta"].item()
            assert [frame["ts"] for frame in meta["frames"]] == times.tolist()
            assert (meta["meta"]["res_x"], meta["meta"]["res_y"]) == (WIDTH, HEIGHT)
            index, step = npz["index"], float(npz["discretization"])
            t = npz["events"][:, 0]
            assert np.all(t[index] >= t[0] + step * np.arange(len(index)) - 1e-9)

    def test_untrusted_refuses_to_unpickle(self, saved):
        path, _ = saved
        with pytest.raises(
            ReaderError, match=r"seq\.npz: the mask timestamps come from 'meta'.*trusted=True"
        ):
            load_evimo(path)

    def test_load_events_needs_no_trust(self, saved):
        path, (events, *_) = saved
        np.testing.assert_array_equal(load_events(path), events)
        np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(path, 64))), events)
        assert read_sensor_size(path) == (HEIGHT, WIDTH)

    def test_ids_round_to_the_nearest_thousand(self, tmp_path, saved):
        path, _ = saved
        with np.load(path, allow_pickle=True) as npz:
            content = dict(npz)
        content["mask"] = content["mask"].copy()
        content["mask"][0, 0, :3] = [998, 1499, 23004]
        np.savez(tmp_path / "noisy.npz", **content)
        assert load_evimo(tmp_path / "noisy.npz", trusted=True).masks[0, 0, :3].tolist() == [1, 1, 23]

    def test_default_calibration(self, tmp_path, sequence):
        path = save_evimo(tmp_path / "seq.npz", *sequence[:3])
        loaded = load_evimo(path, trusted=True)
        np.testing.assert_array_equal(loaded.D, np.zeros(4))
        assert loaded.K[0, 0] == loaded.K[1, 1] == max(HEIGHT, WIDTH)
        assert tuple(loaded.K[:2, 2]) == ((WIDTH - 1) / 2, (HEIGHT - 1) / 2)

    def test_inputs_are_not_modified(self, tmp_path, sequence):
        copies = [np.copy(item) for item in sequence]
        save_evimo(tmp_path / "seq.npz", *sequence[:3], K=sequence[3], D=sequence[4])
        for item, copy in zip(sequence, copies, strict=True):
            np.testing.assert_array_equal(item, copy)

    @pytest.mark.parametrize("missing", ["mask", "meta"])
    def test_missing_key(self, tmp_path, saved, missing):
        path, _ = saved
        with np.load(path, allow_pickle=True) as npz:
            content = {key: npz[key] for key in npz.files if key != missing}
        np.savez(tmp_path / "bad.npz", **content)
        with pytest.raises(ReaderError, match=rf"not an EV-IMO npz: missing key\(s\) \['{missing}'\]"):
            load_evimo(tmp_path / "bad.npz", trusted=True)

    def test_frame_count_mismatch(self, tmp_path, saved):
        path, _ = saved
        with np.load(path, allow_pickle=True) as npz:
            content = dict(npz)
        content["mask"] = content["mask"][:2]
        np.savez(tmp_path / "bad.npz", **content)
        with pytest.raises(ReaderError, match="'meta' lists 3 frames but 'mask' holds 2"):
            load_evimo(tmp_path / "bad.npz", trusted=True)

    def test_truncated(self, tmp_path, saved):
        path, _ = saved
        path.write_bytes(path.read_bytes()[:500])
        with pytest.raises(ReaderError, match=r"seq\.npz: cannot read EV-IMO npz file"):
            load_evimo(path, trusted=True)

    def test_missing_file(self, tmp_path):
        with pytest.raises(ReaderError, match="no such file"):
            load_evimo(tmp_path / "absent.npz", trusted=True)

    def test_save_rejects_bad_masks(self, tmp_path, sequence):
        events, masks, times, _, _ = sequence
        with pytest.raises(ShapeError, match="mask_times_s"):
            save_evimo(tmp_path / "s.npz", events, masks, times[:2])
        with pytest.raises(ShapeError, match=r"integer object ids in \[0, 65\]"):
            save_evimo(tmp_path / "s.npz", events, masks * 10, times)
        with pytest.raises(ShapeError, match=r"K must be \(3, 3\)"):
            save_evimo(tmp_path / "s.npz", events, masks, times, K=np.eye(2))
        with pytest.raises(EventFormatError, match="outside the sensor"):
            save_evimo(tmp_path / "s.npz", events, masks[:, :10], times)
