"""The EVIMO2v2 folder reader, on folders written here in the dataset's layout."""

from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.errors import ReaderError
from evseg_torch.evaluation.evimo import EVALUATED, evaluate_evimo
from evseg_torch.io import (
    EvimoSequence,
    iter_event_chunks,
    load_events,
    load_evimo2,
    read_sensor_size,
    read_time_span,
    reader_for,
)
from tests.helpers.io import HEIGHT, WIDTH, make_events

FRAME_IDS = [3, 4, 5]


def write_evimo2(folder, events, masks, times_s, frame_ids=FRAME_IDS):
    """The EVIMO2v2 layout: three event .npy files, dataset_info.npz (pickled meta), dataset_mask.npz."""
    folder.mkdir(parents=True)
    np.save(folder / "dataset_events_t.npy", events["t"] * 1e-6)
    np.save(folder / "dataset_events_xy.npy", np.column_stack([events["x"], events["y"]]).astype(np.uint16))
    np.save(folder / "dataset_events_p.npy", (events["p"] > 0).astype(np.uint8))
    meta = {
        "frames": [{"id": i, "ts": float(t), "cam": {}} for i, t in zip(frame_ids, times_s, strict=True)],
        "meta": {"res_x": masks.shape[2], "res_y": masks.shape[1], "fx": 100.0},
    }
    np.savez(folder / "dataset_info.npz", K=np.eye(3), D=np.zeros(4), meta=np.array(meta, dtype=object))
    np.savez_compressed(
        folder / "dataset_mask.npz", **{f"mask_{i:010d}": m for i, m in zip(frame_ids, masks, strict=True)}
    )
    return folder


@pytest.fixture
def events():
    return make_events(n=800, t0_us=1_500_000)


@pytest.fixture
def masks():
    masks = np.zeros((3, HEIGHT, WIDTH), dtype=np.uint16)
    masks[:, 20:40, 30:60] = 22  # EVIMO2 object ids
    return masks


def _times(events):
    return events["t"][[200, 400, 600]] * 1e-6


def test_events_of_the_folder(tmp_path, events, masks):
    folder = write_evimo2(tmp_path / "left_camera" / "seq", events, masks, _times(events))
    assert reader_for(folder) == "EVIMO2v2 sequence folder"
    np.testing.assert_array_equal(load_events(folder), events)
    assert read_sensor_size(folder) == (HEIGHT, WIDTH)  # the masks' image size
    chunks = list(iter_event_chunks(folder, chunk_size=300))
    assert [len(c) for c in chunks] == [300, 300, 200]
    np.testing.assert_array_equal(np.concatenate(chunks), events)
    assert read_time_span(folder) == (int(events["t"][0]), int(events["t"][-1]))  # progress bars' total


def test_samsung_mono_polarity_is_flipped(tmp_path, events, masks):
    folder = write_evimo2(tmp_path / "samsung_mono" / "imo" / "eval" / "seq", events, masks, _times(events))
    np.testing.assert_array_equal(load_events(folder)["p"], -events["p"])
    as_stored = load_evimo2(folder, trusted=True, flip_polarity=False)
    np.testing.assert_array_equal(as_stored.events["p"], events["p"])


def test_ground_truth(tmp_path, events, masks):
    masks[1, 0, 0] = 7
    folder = write_evimo2(tmp_path / "seq", events, masks, _times(events))
    sequence = load_evimo2(folder, trusted=True)
    assert isinstance(sequence, EvimoSequence)
    np.testing.assert_array_equal(sequence.events, events)
    np.testing.assert_array_equal(sequence.masks, masks)
    np.testing.assert_allclose(sequence.mask_times_s, _times(events))
    assert sequence.sensor_size == (HEIGHT, WIDTH) and sequence.K.shape == (3, 3)


def test_evaluate_scores_it(tmp_path, events, masks):
    sequence = load_evimo2(write_evimo2(tmp_path / "seq", events, masks, _times(events)), trusted=True)

    def oracle(window, t_ref):
        inside = masks[0, window["y"], window["x"]] > 0
        return SimpleNamespace(
            labels=inside.astype(np.int64), warped_xy=np.column_stack([window["x"], window["y"]]) * 1.0
        )

    results = evaluate_evimo(oracle, sequence, window_ms=4, min_events=10)
    assert [r.status for r in results] == [EVALUATED] * 3
    assert all(r.event_iou == r.event_wise_iou == 1.0 for r in results)


def test_untrusted_meta_is_not_unpickled(tmp_path, events, masks):
    folder = write_evimo2(tmp_path / "seq", events, masks, _times(events))
    with pytest.raises(ReaderError, match="pass trusted=True"):
        load_evimo2(folder)


def test_missing_mask(tmp_path, events, masks):
    folder = write_evimo2(tmp_path / "seq", events, masks, _times(events), frame_ids=[3, 4, 5])
    np.savez(folder / "dataset_mask.npz", mask_0000000003=masks[0])
    with pytest.raises(ReaderError, match="2 of 3 frames have no mask, the first 'mask_0000000004'"):
        load_evimo2(folder, trusted=True)


def test_mismatched_event_files(tmp_path, events, masks):
    folder = write_evimo2(tmp_path / "seq", events, masks, _times(events))
    np.save(folder / "dataset_events_p.npy", np.ones(5, dtype=np.uint8))
    with pytest.raises(ReaderError, match=r"seq: .*for one N, got \(800,\), \(800, 2\), \(5,\)"):
        load_events(folder)


def test_not_a_sequence(tmp_path):
    with pytest.raises(ReaderError, match=r"no dataset_events_t\.npy"):
        load_evimo2(tmp_path, trusted=True)
    with pytest.raises(ReaderError, match="folder of no known layout"):
        reader_for(tmp_path)


def test_evseg_segment_takes_the_folder(tmp_path, events, masks):
    from evseg_torch.app.cli import main

    folder = write_evimo2(tmp_path / "seq", events, masks, _times(events))
    assert main(["--quiet", "segment", str(folder), "--out", str(tmp_path / "out"), "--window-ms", "50"]) == 0
    labels = np.load(tmp_path / "out" / "seq" / "labels.npz")["labels"]
    assert labels.shape == (len(events),)
