import cv2
import pytest
import torch

from evseg_torch.app.cli import main
from evseg_torch.app.threads import set_threads
from evseg_torch.app.workers import WindowPool
from evseg_torch.errors import ConfigError
from evseg_torch.pipeline import CascadedSegmenter


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads(), cv2.getNumThreads()
    yield
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])


def test_sets_torch_and_opencv(restore_threads):
    for threads in (2, 1):
        set_threads(threads)
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (threads, threads)


def test_bad_counts_raise():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="threads"):
            set_threads(bad)


def test_window_workers_use_one_thread_of_each(restore_threads):
    # OpenCV's own pool would otherwise take every core in every worker.
    set_threads(2)
    with WindowPool(CascadedSegmenter((30, 40)), 2) as pool:
        assert pool._pool.apply(cv2.getNumThreads) == 1
        assert pool._pool.apply(torch.get_num_threads) == 1


def test_command_line_threads_set_both(restore_threads, tmp_path):
    set_threads(1)
    args = ["--quiet", "--threads", "2", "simulate", "--out", str(tmp_path), "--sensor-size", "30x40"]
    assert main(args) == 0
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)
