import numpy as np
import pytest

from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.data import SegmentEvents
from evseg_torch.errors import ConfigError, EventFormatError
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene

SENSOR = (90, 120)  # (H, W)
TONIC_SENSOR = (120, 90, 2)  # tonic's (W, H, P)


@pytest.fixture(scope="module")
def scene():
    return make_scene(SENSOR, 0.03, n_objects=1, rng=0)


@pytest.fixture(scope="module")
def segmenter():
    return CascadedSegmenter(SENSOR)


@pytest.fixture(scope="module")
def early(scene, segmenter):
    """The scene's first 1500 events, and their labels segmented directly."""
    return scene.events[:1500], segmenter(scene.events[:1500]).labels


def _tonic_events(scene, dtype) -> np.ndarray:
    """The scene's events in a tonic dtype, with the true layer as an extra field ``gt``."""
    dtype = np.dtype([*((name, dtype[name]) for name in dtype.names), ("gt", "<i8")])
    events = np.zeros(len(scene.events), dtype=dtype)
    for name in ("x", "y", "t"):
        events[name] = scene.events[name]
    events["p"] = scene.events["p"] > 0
    events["gt"] = scene.labels
    return events


class TestWithTonic:
    def test_compose_with_tonic_transforms(self, scene, segmenter):
        tonic = pytest.importorskip("tonic")
        events = _tonic_events(scene, tonic.io.events_struct)
        transforms = tonic.transforms
        denoise = transforms.Denoise(filter_time=3000)
        out = transforms.Compose([denoise, SegmentEvents(segmenter=segmenter)])(events)
        kept = denoise(events)
        assert out.dtype.names == ("x", "y", "t", "p", "gt", "label") and out["label"].dtype == np.int64
        for name in kept.dtype.names:
            np.testing.assert_array_equal(out[name], kept[name])
        np.testing.assert_array_equal(out["label"], segmenter(kept).labels)
        frames = transforms.ToFrame(sensor_size=TONIC_SENSOR, n_time_bins=3)(out)
        assert frames.shape == (3, 2, *SENSOR)

    @pytest.mark.parametrize("dataset", ["events_struct", "DVSGesture", "NMNIST"])
    def test_tonic_dtypes(self, scene, segmenter, early, dataset):
        tonic = pytest.importorskip("tonic")
        dtype = (
            tonic.io.events_struct if dataset == "events_struct" else getattr(tonic.datasets, dataset).dtype
        )
        events = _tonic_events(scene, np.dtype(dtype))[: len(early[0])]
        out = SegmentEvents(segmenter=segmenter)(events)
        np.testing.assert_array_equal(out["label"], early[1])
        assert out.dtype.names[:-1] == events.dtype.names


class TestWindows:
    def test_long_samples_are_segmented_window_by_window(self, scene):
        config = replace_config(SegmenterConfig(), window_ms=10)
        out = SegmentEvents(TONIC_SENSOR, config=config)(scene.events)
        results = list(CascadedSegmenter(SENSOR, config).stream(scene.events, window_ms=10))
        assert len(results) == 3
        first, seen = 0, set()
        for result in results:
            labels = out["label"][result.offset : result.offset + len(result.labels)]
            np.testing.assert_array_equal(labels, result.labels + first)
            assert seen.isdisjoint(labels.tolist())
            seen |= set(labels.tolist())
            first += len(result.models)
        assert (out["label"] >= 0).all()

    def test_windows_of_too_few_events_are_unlabelled(self, scene):
        config = replace_config(SegmenterConfig(), window_ms=10, min_events=10**6)
        out = SegmentEvents(TONIC_SENSOR, config=config)(scene.events)
        assert (out["label"] == -1).all()


class TestCall:
    def test_empty_sample(self, segmenter):
        events = np.zeros(0, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])
        out = SegmentEvents(segmenter=segmenter)(events)
        assert out.shape == (0,) and out.dtype.names == ("x", "y", "t", "p", "label")

    def test_input_is_left_alone_and_an_existing_field_overwritten(self, scene, segmenter):
        events = scene.events[:600]
        source = events.copy()
        once = SegmentEvents(segmenter=segmenter, field="cluster")(events)
        twice = SegmentEvents(segmenter=segmenter, field="cluster")(once)
        np.testing.assert_array_equal(events, source)
        assert twice is not once and twice.dtype == once.dtype
        np.testing.assert_array_equal(twice, once)


class TestErrors:
    def test_sensor_size_or_segmenter(self, segmenter):
        with pytest.raises(ConfigError, match="exactly one of sensor_size"):
            SegmentEvents()
        with pytest.raises(ConfigError, match="exactly one of sensor_size"):
            SegmentEvents(TONIC_SENSOR, segmenter=segmenter)
        with pytest.raises(ConfigError, match="config configures a segmenter built from sensor_size"):
            SegmentEvents(segmenter=segmenter, config=SegmenterConfig())

    def test_not_a_structured_array(self, segmenter):
        with pytest.raises(EventFormatError, match="1-D structured event array"):
            SegmentEvents(segmenter=segmenter)(np.zeros((10, 4)))

    def test_float_timestamps(self, segmenter):
        events = np.zeros(10, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
        with pytest.raises(EventFormatError, match="t must be integer microseconds"):
            SegmentEvents(segmenter=segmenter)(events)

    def test_events_outside_the_sensor(self, scene):
        with pytest.raises(EventFormatError, match="outside the sensor"):
            SegmentEvents((60, 90, 2))(scene.events)
