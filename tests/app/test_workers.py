"""A stream's windows shared out among worker processes give the results of one process."""

import numpy as np
import pytest

from evseg_torch.app.threads import set_threads
from evseg_torch.app.workers import WindowPool
from evseg_torch.errors import ConfigError
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene


def test_stream_workers_give_the_results_of_one_process(one_thread):
    """Two processes share out each batch's windows; every window's result is the one-process result."""
    set_threads(1)  # workers forked while OpenCV runs its own thread pool would hang in it
    scene = make_scene((90, 120), 0.15, n_objects=2, n_events=6000, rng=5)
    segmenter = CascadedSegmenter((90, 120))
    one = list(segmenter.stream(scene.events, window_ms=30, batch_size=3))
    with WindowPool(segmenter, 2, batch_size=3) as pool:
        shared = list(
            segmenter.stream(scene.events, window_ms=30, batch_size=3, segment_windows=pool.segment)
        )
    assert len(one) == len(shared) == 5
    for a, b in zip(one, shared, strict=True):
        assert (a.offset, a.window_index) == (b.offset, b.window_index)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.models, b.models)


@pytest.mark.parametrize(("workers", "batch_size"), [(3, 2), (0, None), (1.5, None), (True, None)])
def test_worker_counts_are_checked(workers, batch_size):
    with pytest.raises(ConfigError, match="workers"):
        WindowPool(CascadedSegmenter((30, 40)), workers, batch_size=batch_size)
