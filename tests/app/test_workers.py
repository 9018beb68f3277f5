"""A stream's windows shared out among worker processes give the results of one process."""

import subprocess
import sys

import numpy as np
import pytest

from evseg_torch.app.workers import WindowPool
from evseg_torch.errors import ConfigError
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene


def test_stream_workers_give_the_results_of_one_process(one_thread):
    """Two processes share out each batch's windows; every window's result is the one-process result."""
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


def test_a_pool_forked_after_opencv_ran_its_threads_works():
    # A worker forked while OpenCV's thread pool exists would hang in its first cv2.setNumThreads; the pool
    # winds OpenCV down to one thread for the fork. A fresh process, so that its threads start as a user's.
    code = """
import cv2, numpy as np
from evseg_torch.app.workers import WindowPool
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene
cv2.setNumThreads(2)
image = np.random.default_rng(0).random((500, 500), dtype=np.float32)
for _ in range(3):
    cv2.GaussianBlur(image, (15, 15), 3)
events = make_scene((60, 80), 0.03, n_objects=1, n_events=2000, rng=0).events
segmenter = CascadedSegmenter((60, 80))
segmenter(events)
with WindowPool(segmenter, 2, batch_size=2) as pool:
    print(len(pool.segment([events, events], None)), cv2.getNumThreads())
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["2", "2"]  # both windows segmented, the parent's threads restored
