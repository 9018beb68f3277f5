"""The one setting that chooses the compiled kernels (evseg_torch.backend)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from evseg_torch import backend
from evseg_torch.backend import get_backend, kernel, set_backend, using_backend
from evseg_torch.errors import ConfigError


def test_torch_takes_no_kernel_and_the_setting_returns():
    before = get_backend()
    with using_backend("torch"):
        assert get_backend() == "torch"
        assert kernel("fit.loss_and_grad") is None
    assert get_backend() == before


def test_auto_and_numba_take_the_kernels_where_numba_is_installed():
    fit = pytest.importorskip("evseg_torch.kernels.fit")
    for name in ("auto", "numba"):
        with using_backend(name):
            assert kernel("fit.loss_and_grad") is fit.loss_and_grad


@pytest.mark.parametrize("name", ["cuda", "", "Torch"])
def test_unknown_settings_are_refused(name):
    with pytest.raises(ConfigError, match="backend must be one of auto, numba, torch"):
        set_backend(name)


def test_numba_without_the_package_is_refused(monkeypatch):
    monkeypatch.setattr(backend, "_numba_installed", lambda: False)
    with pytest.raises(ConfigError, match="needs the numba package"):
        set_backend("numba")


@pytest.mark.parametrize(
    ("value", "expected"), [("torch", "torch"), ("bogus", "EVSEG_BACKEND must be one of")]
)
def test_the_environment_sets_the_start(value, expected):
    code = (
        "from evseg_torch.backend import get_backend\n"
        "try:\n    print(get_backend())\nexcept Exception as error:\n    print(error)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "EVSEG_BACKEND": value},
        check=True,
    )
    assert expected in out.stdout


def test_every_kernel_the_package_asks_for_exists():
    # A kernel that failed to import would leave its step to the tensor code without a word.
    pytest.importorskip("numba")
    root = Path(backend.__file__).parent
    names = {
        name for path in root.rglob("*.py") for name in re.findall(r'kernel\("([\w.]+)"\)', path.read_text())
    }
    assert len(names) >= 7
    with using_backend("numba"):
        for name in names:
            assert callable(kernel(name)), name
