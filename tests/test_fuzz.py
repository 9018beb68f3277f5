"""Reliability fuzzing of the readers and the segmenter with seeded random and hand-picked extreme inputs.

Every case must end in a valid result or in one of our own errors (:class:`~evseg_torch.errors.EvsegError`
subclasses) with a one-line message: no other exception, no hang, no silent garbage. Cases are generated
from fixed seeds at collection, so each has a stable id that names it and a failure replays exactly.
"""

import numpy as np
import pytest

from evseg_torch.errors import EventFormatError, EvsegError, ModelError, ReaderError
from evseg_torch.events import EVENT_DTYPE
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size, save_evimo
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene
from tests.helpers.io import (
    aedat2_bytes,
    make_events,
    write_h5_dsec,
    write_h5_event_utils,
    write_npy,
    write_npy_structured,
    write_npz_columns,
    write_npz_events,
    write_txt,
)

# ---------------------------------------------------------------------------------------------------
# Readers


def _write_evimo(path, events):
    masks = np.zeros((1, 120, 128), dtype=np.uint8)
    save_evimo(path, events, masks, np.array([events["t"][0] * 1e-6]))


def _write_aedat2(path, events):
    path.write_bytes(aedat2_bytes(events))


def _write_aedat4_header(path, events):
    # No AEDAT 4 encoder is installed: a valid header with whatever follows exercises the decoder.
    path.write_bytes(b"#!AER-DAT4.0\r\n" + events.tobytes())


VALID_WRITERS = {
    ".txt": [write_txt],
    ".npy": [write_npy, write_npy_structured],
    ".npz": [write_npz_columns, write_npz_events, _write_evimo],
    ".h5": [write_h5_event_utils, write_h5_dsec],
    ".aedat": [_write_aedat2],
    ".aedat4": [_write_aedat4_header],
}
MUTATIONS = ("random", "truncated", "garbled", "prefix")
MUTATION_SEEDS = range(6)


def _mutated_bytes(path, suffix: str, mutation: str, seed: int) -> bytes:
    rng = np.random.default_rng([seed, MUTATIONS.index(mutation), list(VALID_WRITERS).index(suffix)])
    if mutation == "random":
        return rng.bytes(int(rng.choice([0, 1, 7, 64, 1000, 20_000])))
    writers = VALID_WRITERS[suffix]
    writers[seed % len(writers)](path, make_events(int(rng.integers(1, 300)), seed=seed))
    data = np.frombuffer(path.read_bytes(), dtype=np.uint8).copy()
    if mutation == "truncated":
        return data[: int(rng.integers(0, len(data)))].tobytes()
    if mutation == "garbled":
        where = rng.integers(0, len(data), int(rng.integers(1, 33)))
        data[where] = rng.integers(0, 256, len(where), dtype=np.uint8)
        return data.tobytes()
    return data[: int(rng.integers(1, 65))].tobytes() + rng.bytes(int(rng.integers(0, 4000)))


def _text_cases() -> dict[str, str]:
    line = "0.000100 3 4 1\n"
    return {
        "empty": "",
        "comments_only": "# t x y p\n# nothing\n",
        "blank_lines": "\n\n   \n",
        "one_event": line,
        "duplicates": line * 200,
        "nan_p": "0.1 1 2 nan\n",
        "nan_t": "nan 1 2 1\n",
        "inf_t": "inf 1 2 1\n",
        "huge_t": "1e300 1 2 1\n",
        "t_beyond_int64_us": "1e14 1 2 1\n",
        "negative_t": "-5.0 1 2 1\n0.0 1 2 1\n",
        "negative_x": "0.1 -1 2 1\n",
        "huge_x": "0.1 40000 2 1\n",
        "x_beyond_int64": "0.1 1e30 2 1\n",
        "fractional_x": "0.1 1.5 2 1\n",
        "polarity_2": "0.1 1 2 2\n",
        "unsorted": "0.2 1 2 1\n0.1 1 2 1\n",
        "three_columns": "0.1 1 2\n",
        "five_columns": "0.1 1 2 1 7\n",
        "ragged": "0.1 1 2 1\n0.2 1 2\n",
        "words": "time x y polarity\n",
        "hex": "0x10 1 2 1\n",
        "utf8_junk": "0.1 1 2 1 \u00e9\u4e2d\n",
        "nul_bytes": "0.1 1\x00 2 1\n",
        "crlf": "0.1 1 2 1\r\n0.2 3 4 0\r\n",
        "commas": "0.1,1,2,1\n",
    }


def _npy_cases() -> dict[str, np.ndarray]:
    good = np.array([[0.1, 1, 2, 1], [0.2, 3, 4, 0]])
    structured = np.zeros(3, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    structured["t"] = [1, 2, np.iinfo(np.uint64).max]
    floating_t = np.zeros(2, dtype=[("t", "<f8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    missing_field = np.zeros(2, dtype=[("t", "<i8"), ("x", "<u2"), ("p", "u1")])
    return {
        "empty_rows": np.zeros((0, 4)),
        "one_row": good[:1],
        "flat": np.arange(4.0),
        "scalar": np.float64(3.0),
        "three_columns": good[:, :3],
        "three_dims": good[None],
        "nan": np.array([[np.nan, 1, 2, 1]]),
        "inf_x": np.array([[0.1, np.inf, 2, 1]]),
        "huge_t_seconds": np.array([[1e20, 1, 2, 1]]),
        "t_beyond_int64_us": np.array([[1e14, 1, 2, 1], [2e14, 1, 2, 1]]),
        "huge_x": np.array([[0.1, 1e9, 2, 1]]),
        "negative_y": np.array([[0.1, 1, -2, 1]]),
        "unsorted": good[::-1].copy(),
        "complex": good.astype(np.complex128),
        "strings": np.array([["a", "b", "c", "d"]]),
        "bools": np.ones((3, 4), dtype=bool),
        "uint64_t_max": structured,
        "float_t_field": floating_t,
        "missing_field": missing_field,
        "object": np.array([[None, 1, 2, 3]], dtype=object),
    }


def _write_semantic(path, suffix: str, name: str) -> None:
    if suffix == ".txt":
        path.write_bytes(_text_cases()[name].encode("utf-8"))
    elif suffix == ".npy":
        data = _npy_cases()[name]
        np.save(path, data, allow_pickle=data.dtype == object)
    else:
        _NPZ_H5_AEDAT[name](path)


def _npz(**arrays):
    return lambda path: np.savez(path, **arrays)


def _h5(**datasets):
    def write(path):
        import h5py

        with h5py.File(path, "w") as file:
            for key, value in datasets.items():
                if key == "sensor_resolution":
                    file.attrs[key] = value
                else:
                    file.create_dataset(key, data=value)

    return write


def _aedat(data: bytes):
    return lambda path: path.write_bytes(data)


_EVENTS = make_events(20)
_N = len(_EVENTS)
_AEDAT = aedat2_bytes(_EVENTS)
_HEADER_END = _AEDAT.index(b"# end\r\n") + len(b"# end\r\n")
_NPZ_H5_AEDAT = {
    # .npz
    "npz_no_arrays": _npz(),
    "npz_unrelated_keys": _npz(a=np.zeros(3), b=np.ones(2)),
    "npz_events_wrong_shape": _npz(events=np.zeros((5, 3))),
    "npz_events_nan": _npz(events=np.full((5, 4), np.nan)),
    "npz_columns_unequal": _npz(t_us=np.arange(5), x=np.zeros(4), y=np.zeros(5), p=np.ones(5)),
    "npz_zero_width": _npz(t_us=np.arange(5), x=np.zeros(5), y=np.zeros(5), p=np.ones(5), width=0, height=0),
    "npz_negative_height": _npz(
        t_us=np.arange(2), x=np.zeros(2), y=np.zeros(2), p=np.ones(2), width=4, height=-3
    ),
    "npz_huge_size": _npz(
        t_us=np.arange(2), x=np.zeros(2), y=np.zeros(2), p=np.ones(2), width=10**12, height=5
    ),
    "npz_size_array": _npz(
        t_us=np.arange(2), x=np.zeros(2), y=np.zeros(2), p=np.ones(2), width=np.arange(3), height=4
    ),
    "npz_events_object": lambda path: np.savez(path, events=np.array([[None] * 4], dtype=object)),
    "npz_evimo_mask_only": _npz(events=np.zeros((0, 4)), mask=np.zeros((1, 4, 4), np.uint16)),
    # .h5
    "h5_empty_file": _h5(),
    "h5_unrelated": _h5(**{"foo/bar": np.zeros(3)}),
    "h5_unequal": _h5(
        **{
            "events/xs": np.zeros(3),
            "events/ys": np.zeros(2),
            "events/ts": np.zeros(3),
            "events/ps": np.ones(3),
        }
    ),
    "h5_empty_datasets": _h5(
        **{
            "events/xs": np.zeros(0),
            "events/ys": np.zeros(0),
            "events/ts": np.zeros(0),
            "events/ps": np.zeros(0),
        }
    ),
    "h5_strings": _h5(
        **{
            "events/xs": np.array([b"a"]),
            "events/ys": np.zeros(1),
            "events/ts": np.zeros(1),
            "events/ps": np.ones(1),
        }
    ),
    "h5_nan_t": _h5(
        **{
            "events/xs": np.zeros(2),
            "events/ys": np.zeros(2),
            "events/ts": np.array([np.nan, 1.0]),
            "events/ps": np.ones(2),
        }
    ),
    "h5_bad_resolution": _h5(
        **{
            "events/xs": np.zeros(2),
            "events/ys": np.zeros(2),
            "events/ts": np.arange(2.0),
            "events/ps": np.ones(2),
            "sensor_resolution": np.array([0, -4, 7]),
        }
    ),
    "h5_2d_dataset": _h5(
        **{
            "events/xs": np.zeros((2, 2)),
            "events/ys": np.zeros(2),
            "events/ts": np.arange(2.0),
            "events/ps": np.ones(2),
        }
    ),
    "h5_dsec_no_offset": _h5(
        **{
            "events/x": np.zeros(2, np.uint16),
            "events/y": np.zeros(2, np.uint16),
            "events/t": np.arange(2, dtype=np.uint32),
            "events/p": np.ones(2, np.uint8),
        }
    ),
    # .aedat
    "aedat_header_only": _aedat(_AEDAT[:_HEADER_END]),
    "aedat_partial_record": _aedat(_AEDAT[: _HEADER_END + 8 * (_N // 2) + 3]),
    "aedat_version_3": _aedat(_AEDAT.replace(b"#!AER-DAT2.0", b"#!AER-DAT3.1")),
    "aedat_other_chip": _aedat(_AEDAT.replace(b"DVS128", b"DAVIS346")),
    "aedat_no_header": _aedat(_AEDAT[_HEADER_END:]),
    "aedat_time_wraps": _aedat(_AEDAT[:_HEADER_END] + _AEDAT[_HEADER_END:][::-1]),
    "aedat_unterminated_header": _aedat(b"#!AER-DAT2.0\r\n# AEChip: x\r\n" * 50),
}
_SEMANTIC_SUFFIX = {"npz": ".npz", "h5": ".h5", "aedat": ".aedat"}


def _reader_cases():
    cases = [
        (suffix, mutation, seed, f"{suffix[1:]}-{mutation}-{seed}")
        for suffix in VALID_WRITERS
        for mutation in MUTATIONS
        for seed in MUTATION_SEEDS
    ]
    semantic = [(".txt", name) for name in _text_cases()] + [(".npy", name) for name in _npy_cases()]
    semantic += [(_SEMANTIC_SUFFIX[name.split("_")[0]], name) for name in _NPZ_H5_AEDAT]
    cases += [(suffix, "semantic", name, f"{suffix[1:]}-{name}") for suffix, name in semantic]
    return [
        pytest.param(
            suffix,
            mutation,
            case,
            id=name,
        )
        for suffix, mutation, case, name in cases
    ]


def _assert_canonical(events: np.ndarray, sensor_size) -> None:
    assert isinstance(events, np.ndarray) and events.dtype == EVENT_DTYPE and events.ndim == 1
    assert len(events) > 0
    assert np.all(np.diff(events["t"]) >= 0)
    assert np.all(events["x"] >= 0) and np.all(events["y"] >= 0)
    assert set(np.unique(events["p"]).tolist()) <= {-1, 1}
    if sensor_size is not None:
        assert np.all(events["y"] < sensor_size[0]) and np.all(events["x"] < sensor_size[1])


def _outcome(read):
    """The events ``read`` returns, or our error; any other exception fails the test."""
    try:
        return read()
    except (ReaderError, EventFormatError) as err:
        return err


@pytest.mark.parametrize(("suffix", "mutation", "case"), _reader_cases())
def test_reader(tmp_path, suffix, mutation, case):
    path = tmp_path / f"events{suffix}"
    if mutation == "semantic":
        _write_semantic(path, suffix, case)
    else:
        path.write_bytes(_mutated_bytes(path, suffix, mutation, case))
    events = _outcome(lambda: load_events(path))
    chunks = _outcome(lambda: np.concatenate(list(iter_event_chunks(path, chunk_size=7))))
    size = _outcome(lambda: read_sensor_size(path))
    assert size is None or isinstance(size, EvsegError) or (len(size) == 2 and min(size) > 0)
    if isinstance(events, EvsegError):
        message = str(events)
        assert message.startswith(str(path)) and "\n" not in message
        assert isinstance(chunks, EvsegError), "iter_event_chunks read a file that load_events rejects"
        return
    _assert_canonical(events, size)
    np.testing.assert_array_equal(chunks, events)


def test_unsigned_times_beyond_int64_are_rejected(tmp_path):
    data = np.zeros(2, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    data["t"] = [2**63 + 5, 2**63 + 6]
    np.save(tmp_path / "events.npy", data)
    with pytest.raises(EventFormatError):
        load_events(tmp_path / "events.npy")


# ---------------------------------------------------------------------------------------------------
# Segmenter


def _events(t, x, y, p=1) -> np.ndarray:
    events = np.zeros(len(t), dtype=EVENT_DTYPE)
    events["t"], events["x"], events["y"], events["p"] = t, x, y, p
    return events


def _uniform(rng, n, size, t):
    return _events(t, rng.integers(0, size[1], n), rng.integers(0, size[0], n), rng.choice([-1, 1], n))


def _named_windows():
    """Hand-picked extremes: ``name -> (sensor_size, events or raw input, segmenter kwargs)``."""
    rng = np.random.default_rng(7)
    size = (48, 64)
    ramp = np.arange(1000) * 30
    base = _uniform(rng, 1000, size, ramp)
    return {
        "zero_events": (size, np.zeros(0, dtype=EVENT_DTYPE), {}),
        "one_event": (size, _events([5], [3], [4]), {}),
        "two_events": (size, _events([5, 6], [3, 4], [4, 5]), {}),
        "one_pixel": (size, _events(ramp, 7, 9), {}),
        "one_time": (size, _uniform(rng, 1000, size, np.zeros(1000, np.int64)), {}),
        "two_times": (size, _uniform(rng, 1000, size, np.repeat([0, 1], 500)), {}),
        "duplicated": (size, np.repeat(base[::10], 10), {}),
        "last_pixel": (size, _events(ramp, size[1] - 1, size[0] - 1), {}),
        "one_row": (size, _events(ramp, rng.integers(0, size[1], 1000), 0), {}),
        "one_column": (size, _events(ramp, 0, rng.integers(0, size[0], 1000)), {}),
        "sensor_4x4": ((4, 4), _uniform(rng, 500, (4, 4), np.arange(500) * 10), {}),
        "sensor_4x300": ((4, 300), _uniform(rng, 500, (4, 300), np.arange(500) * 10), {}),
        "huge_absolute_time": (size, _uniform(rng, 1000, size, 2**62 + ramp), {}),
        "negative_time": (size, _uniform(rng, 1000, size, -(10**12) + ramp), {}),
        "span_of_a_day": (
            size,
            _uniform(rng, 1000, size, np.sort(rng.integers(0, 86_400 * 10**6, 1000))),
            {},
        ),
        "span_beyond_int64": (size, _events([-(2**62) - 1, 2**62], [0, 1], [0, 1]), {}),
        "one_burst": (
            size,
            np.sort(np.concatenate([base, _events(np.full(3000, 15_000), 5, 5)]), order="t"),
            {},
        ),
        "t_ref_far_away": (size, base, {"t_ref": 1e6}),
        "t_ref_negative": (size, base, {"t_ref": -1e3}),
        "t_ref_nan": (size, base, {"t_ref": float("nan")}),
        "t_ref_inf": (size, base, {"t_ref": float("-inf")}),
        "t_ref_beyond_int64": (size, base, {"t_ref": 1e300}),
        "t_ref_string": (size, base, {"t_ref": "0.01"}),
        "initial_models_nan": (size, base, {"initial_models": np.full((2, 4), np.nan)}),
        "initial_models_wrong_width": (size, base, {"initial_models": np.zeros((2, 3))}),
        "initial_models_1d": (size, base, {"initial_models": np.zeros(4)}),
        "initial_models_huge": (size, base, {"initial_models": np.full((2, 4), 1e30)}),
        "initial_models_overflowing": (
            size,
            base,
            {"initial_models": np.array([[1e307, -1e307, 1e307, 1e307]])},
        ),
        "initial_models_empty": (size, base, {"initial_models": np.zeros((0, 4))}),
        "outside_sensor": (size, _events([0, 1], [size[1], 0], [0, 0]), {}),
        "huge_coordinates": (size, np.array([[0.0, 1e9, 2, 1], [1e-3, 1, 2, 0]]), {}),
        "negative_coordinates": (size, np.array([[0.0, -1, 2, 1], [1e-3, 1, 2, 0]]), {}),
        "nan_array": (size, np.array([[np.nan, 1, 2, 1], [1e-3, 1, 2, 0]]), {}),
        "unsorted": (size, base[::-1].copy(), {}),
        "polarity_7": (size, np.array([[0.0, 1, 2, 7], [1e-3, 1, 2, 0]]), {}),
        "float_seconds_list": (size, [[0.0, 1, 2, 1], [1e-3, 3, 4, 0], [2e-3, 5, 6, 1]], {}),
        "string_input": (size, "events", {}),
        "none_input": (size, None, {}),
        "ragged_list": (size, [[0.0, 1, 2], [1e-3, 3, 4, 0]], {}),
    }


def _random_window(seed: int):
    """A seeded random window: size, count, time and space structure all drawn from extremes."""
    rng = np.random.default_rng(seed)
    sizes = [(4, 4), (5, 9), (16, 16), (31, 17), (48, 64), (90, 120), (1, 1), (1, 40), (40, 2)]
    chance = np.array([2, 2, 2, 2, 3, 3, 1, 1, 1], dtype=float)
    height, width = sizes[int(rng.choice(len(sizes), p=chance / chance.sum()))]
    n = int(np.exp(rng.uniform(0, np.log(6000))))
    times = {
        "uniform": lambda: np.sort(rng.integers(0, 30_000, n)),
        "constant": lambda: np.full(n, int(rng.integers(0, 10**9))),
        "few_steps": lambda: np.sort(rng.choice(rng.integers(0, 30_000, 3), n)),
        "bursty": lambda: np.sort(rng.choice(rng.integers(0, 30_000, 5), n) + rng.integers(0, 3, n)),
        "huge_gap": lambda: np.sort(
            np.r_[rng.integers(0, 100, n - n // 2), 10**13 + rng.integers(0, 100, n // 2)]
        ),
        "late": lambda: 2**62 + np.sort(rng.integers(0, 30_000, n)),
    }
    kind = list(times)[int(rng.integers(len(times)))]
    t = times[kind]()
    spaces = {
        "uniform": lambda: (rng.integers(0, width, n), rng.integers(0, height, n)),
        "one_pixel": lambda: (np.full(n, width - 1), np.full(n, height - 1)),
        "blob": lambda: (
            np.clip(rng.normal(width / 2, 2, n), 0, width - 1).astype(int),
            np.clip(rng.normal(height / 2, 2, n), 0, height - 1).astype(int),
        ),
        "moving_edge": lambda: ((np.arange(n) * width // max(n, 1)) % width, rng.integers(0, height, n)),
    }
    space = list(spaces)[int(rng.integers(len(spaces)))]
    x, y = spaces[space]()
    events = _events(t, x, y, rng.choice([-1, 1], n))
    # Half of the windows get a reference time anywhere from well before to well after them.
    kwargs = (
        {"t_ref": float(t[0] + rng.uniform(-2, 2) * (t[-1] - t[0] + 1000)) * 1e-6}
        if rng.random() < 0.5
        else {}
    )
    return (
        (height, width),
        events,
        kwargs,
        f"{height}x{width}-n{n}-{kind}-{space}" + ("-t_ref" if kwargs else ""),
    )


def _scene_window(seed: int):
    """A synthetic scene with moving objects, mangled: events that level one can track, at extremes."""
    rng = np.random.default_rng(1000 + seed)
    size = (48, 64) if seed % 2 else (90, 120)
    scene = make_scene(size, duration=0.02, n_objects=seed % 4, n_events=6000, noise_rate_hz=5.0, rng=seed)
    events = scene.events
    mangles = {
        "as_is": lambda: events,
        "subsampled": lambda: events[
            np.sort(rng.choice(len(events), int(rng.integers(2, 60)), replace=False))
        ],
        "millisecond_times": lambda: _events(
            events["t"] // 1000 * 1000, events["x"], events["y"], events["p"]
        ),
        "two_times": lambda: _events(
            np.where(events["t"] < events["t"][len(events) // 2], 0, 1), events["x"], events["y"]
        ),
        "tripled": lambda: np.repeat(events, 3),
        "hot_pixel": lambda: np.sort(
            np.r_[events, _events(events["t"][::2], 0, 0)], order="t", kind="stable"
        ),
        "one_polarity": lambda: _events(events["t"], events["x"], events["y"], -1),
        "stretched_a_day": lambda: _events(events["t"] * 4000, events["x"], events["y"], events["p"]),
    }
    name = list(mangles)[seed % len(mangles)]
    return size, mangles[name](), {}, f"{size[0]}x{size[1]}-{scene.n_objects}obj-{name}"


def _segmenter_cases():
    cases = []
    for name, (size, data, kwargs) in _named_windows().items():
        cases.append(pytest.param(size, data, kwargs, id=f"named-{name}"))
    for seed in range(60):
        size, data, kwargs, name = _random_window(seed)
        cases.append(pytest.param(size, data, kwargs, id=f"random-{seed}-{name}"))
    for seed in range(16):
        size, data, kwargs, name = _scene_window(seed)
        cases.append(pytest.param(size, data, kwargs, id=f"scene-{seed}-{name}"))
    return cases


def _assert_valid(result, events, sensor_size, t_ref) -> None:
    n = len(events)
    labels, models = result.labels, result.models
    assert labels.shape == (n,) and labels.dtype == np.int64
    assert models.ndim == 2 and models.dtype == np.float64 and np.all(np.isfinite(models))
    k = models.shape[0]
    assert k >= 1 and models.shape[1] == 4  # affine4, the default
    assert np.all((labels >= -1) & (labels < k))
    assert result.warped_xy.shape == (n, 2) and np.all(np.isfinite(result.warped_xy))
    assert result.iwes.shape == (k, *sensor_size) and np.all(np.isfinite(result.iwes))
    assert len(result.feature_labels) == len(result.feature_tracks)
    assert result.sensor_size == sensor_size
    np.testing.assert_array_equal(result.events, events)
    expected_t_ref = events["t"][0] * 1e-6 if t_ref is None else round(t_ref * 1e6) * 1e-6
    assert result.t_ref == pytest.approx(expected_t_ref)


@pytest.mark.parametrize(("sensor_size", "data", "kwargs"), _segmenter_cases())
def test_segmenter(sensor_size, data, kwargs):
    snapshot = data.copy() if isinstance(data, np.ndarray) else None
    try:
        result = CascadedSegmenter(sensor_size)(data, **kwargs)
    except (EventFormatError, ModelError) as err:
        assert str(err) and "\n" not in str(err)
        return
    finally:
        if snapshot is not None:
            np.testing.assert_array_equal(data, snapshot)  # the caller's input is never modified
    _assert_valid(result, result.events, sensor_size, kwargs.get("t_ref"))
    if isinstance(data, np.ndarray) and data.dtype == EVENT_DTYPE:
        np.testing.assert_array_equal(result.events, data)


def test_segmenter_errors_are_ours():
    # The cases above accept only EventFormatError and ModelError; both are EvsegError subclasses.
    assert issubclass(EventFormatError, EvsegError) and issubclass(ModelError, EvsegError)


STREAM_CASES = {
    "default_windows": {},
    "ten_microsecond_windows": {"window_ms": 0.01},
    "sub_microsecond_window": {"window_ms": 1e-4},
    "year_window": {"window_ms": 3.2e10},
    "overlapping": {"window_ms": 10, "stride_ms": 3},
    "sub_microsecond_stride": {"window_ms": 5, "stride_ms": 1e-4},
    "negative_window": {"window_ms": -5},
    "one_event_windows": {"events_per_window": 1},
    "zero_event_windows": {"events_per_window": 0},
    "billion_event_windows": {"events_per_window": 10**9},
    "both_kinds": {"window_ms": 10, "events_per_window": 500},
    "nan_window": {"window_ms": float("nan")},
    "inf_window": {"window_ms": float("inf")},
}


@pytest.fixture(scope="module")
def stream_scene():
    return make_scene((48, 64), duration=0.03, n_objects=1, n_events=3000, rng=2)


@pytest.mark.parametrize("kwargs", list(STREAM_CASES.values()), ids=list(STREAM_CASES))
def test_stream(stream_scene, kwargs):
    events = stream_scene.events
    try:
        results = list(CascadedSegmenter((48, 64)).stream(events, **kwargs))
    except EventFormatError as err:
        assert str(err) and "\n" not in str(err)
        return
    for index, result in enumerate(results):
        window = events[result.offset : result.offset + len(result.events)]
        _assert_valid(result, window, (48, 64), None)
        assert result.window_index >= index


def test_stream_rejects_chunks_out_of_order(stream_scene):
    half = len(stream_scene.events) // 2
    chunks = [stream_scene.events[half:], stream_scene.events[:half]]
    with pytest.raises(EventFormatError, match="decrease"):
        list(CascadedSegmenter((48, 64)).stream(chunks, window_ms=5))


def test_a_million_events_in_one_window():
    rng = np.random.default_rng(0)
    n, size = 10**6, (32, 32)
    events = _uniform(rng, n, size, np.sort(rng.integers(0, 30_000, n)))
    result = CascadedSegmenter(size)(events)
    _assert_valid(result, events, size, None)


def test_same_seed_same_labels():
    # Seed 2 is a scene whose labels depended on the calls made before, when the segmenter held one
    # generator for its whole life.
    scene = make_scene((90, 120), duration=0.03, n_objects=2, n_events=8000, rng=2)
    segmenter = CascadedSegmenter((90, 120), seed=5)
    first, again = segmenter(scene.events), segmenter(scene.events)
    fresh = CascadedSegmenter((90, 120), seed=5)(scene.events)
    assert first.n_clusters >= 2
    for other in (again, fresh):
        np.testing.assert_array_equal(first.labels, other.labels)
        np.testing.assert_array_equal(first.models, other.models)
        np.testing.assert_array_equal(first.feature_labels, other.feature_labels)
