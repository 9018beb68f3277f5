"""Device and dtype fixtures in kornia's manner, and the path to the shared real recordings.

``--device`` / ``EVSEG_TEST_DEVICE`` (cpu, cuda or all) and ``--dtype`` / ``EVSEG_TEST_DTYPE``
(float32, float64 or all) parametrise every test that asks for ``device`` or ``dtype``; an absent
device is skipped, never failed.
"""

import os
from pathlib import Path

import pytest
import torch

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def pytest_addoption(parser):
    parser.addoption("--device", default=os.environ.get("EVSEG_TEST_DEVICE", "cpu"))
    parser.addoption("--dtype", default=os.environ.get("EVSEG_TEST_DTYPE", "float32"))


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        option = metafunc.config.getoption("--device")
        names = ["cpu", "cuda"] if option == "all" else option.split(",")
        metafunc.parametrize("device", names, indirect=True)
    if "dtype" in metafunc.fixturenames:
        option = metafunc.config.getoption("--dtype")
        names = list(_DTYPES) if option == "all" else option.split(",")
        metafunc.parametrize("dtype", names, indirect=True)


@pytest.fixture
def device(request) -> torch.device:
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    return torch.device(request.param)


@pytest.fixture
def dtype(request) -> torch.dtype:
    return _DTYPES[request.param]


@pytest.fixture
def real_data() -> Path:
    """The folder of real recordings; tests that use it are skipped where it is absent."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real recordings not found at {REAL_DATA}")
    return REAL_DATA


@pytest.fixture
def one_thread():
    """One torch thread: batched and solo level two agree bit for bit only when torch splits no reduction
    across threads."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
