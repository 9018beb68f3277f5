"""The canonical event form: validation, conversions, sensor sizes."""

import numpy as np
import pytest
import torch

from evseg_torch.errors import EventFormatError
from evseg_torch.events import (
    EVENT_DTYPE,
    as_events,
    check_sensor_size,
    infer_sensor_size,
    sensor_size_from_tonic,
    sensor_size_to_tonic,
    to_array,
)


def _array(n=5):
    t = np.arange(n) * 1e-3
    return np.column_stack([t, np.arange(n) % 4, np.arange(n) % 3, np.arange(n) % 2]).astype(np.float64)


class TestAsEvents:
    def test_float_array(self):
        ev = as_events(_array(), sensor_size=(3, 4))
        assert ev.dtype == EVENT_DTYPE
        assert ev["t"].tolist() == [0, 1000, 2000, 3000, 4000]
        assert ev["p"].tolist() == [-1, 1, -1, 1, -1]

    @pytest.mark.parametrize(
        "polarity", [np.array([0, 1, 1]), np.array([-1, 1, 1]), np.array([False, True, True])]
    )
    def test_polarity_forms_agree(self, polarity):
        data = np.zeros(3, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", polarity.dtype)])
        data["t"], data["p"] = [1, 2, 3], polarity
        assert as_events(data)["p"].tolist() == [-1, 1, 1]

    def test_aedat_style_on_field(self):
        data = np.zeros(2, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])
        data["on"] = [True, False]
        assert as_events(data)["p"].tolist() == [1, -1]

    def test_round_trip_through_array(self):
        ev = as_events(_array())
        np.testing.assert_array_equal(as_events(to_array(ev)), ev)

    def test_input_not_modified_and_not_returned(self):
        data = _array()
        before = data.copy()
        as_events(data)
        np.testing.assert_array_equal(data, before)
        structured = as_events(data)
        again = as_events(structured)
        assert again is not structured
        np.testing.assert_array_equal(again, structured)

    @pytest.mark.parametrize(
        ("data", "message"),
        [
            (np.zeros((0, 4)), "no events"),
            (np.zeros((3, 3)), r"\(N, 4\)"),
            (np.array([[0.0, 1, 1, np.nan]]), "NaN"),
            (np.array([[np.inf, 1, 1, 1]]), "NaN or inf"),
            (np.array([[0.0, 1.5, 1, 1]]), "non-integer"),
            (np.array([[0.0, -1, 1, 1]]), "negative"),
            (np.array([[0.0, 1, 1, 2]]), "polarity"),
            (np.array([[0.002, 1, 1, 1], [0.001, 1, 1, 1]]), "decrease at event 1"),
            (np.array(["a", "b"]), r"\(N, 4\)"),
            (np.zeros(2, dtype=[("t", "f8"), ("x", "i2"), ("y", "i2"), ("p", "i1")]), "integer microseconds"),
            (np.zeros(2, dtype=[("t", "i8"), ("x", "i2")]), "lack field"),
            (torch.zeros(2, 4), "NumPy"),
        ],
    )
    def test_exception(self, data, message):
        with pytest.raises(EventFormatError, match=message):
            as_events(data)

    def test_outside_sensor(self):
        with pytest.raises(EventFormatError, match=r"x = 3 lies outside the sensor \(W = 3\)"):
            as_events(np.array([[0.0, 3, 1, 1]]), sensor_size=(2, 3))
        with pytest.raises(EventFormatError, match="sensor_size"):
            as_events(np.array([[0.0, 1, 1, 1]]), sensor_size=(0, 3))

    def test_sensor_size_helpers(self):
        assert check_sensor_size([180, 240]) == (180, 240)
        assert sensor_size_from_tonic((240, 180, 2)) == (180, 240)
        assert sensor_size_to_tonic((180, 240)) == (240, 180, 2)
        assert infer_sensor_size(as_events(_array())) == (3, 4)
        with pytest.raises(EventFormatError):
            check_sensor_size("big")
