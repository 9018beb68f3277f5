"""Fixtures of the reader tests: synthetic events, and a file of them in each writable format."""

import numpy as np
import pytest

from tests.helpers.io import WRITERS, make_events


@pytest.fixture
def events() -> np.ndarray:
    return make_events()


@pytest.fixture(params=sorted(WRITERS))
def written(request, tmp_path, events):
    """``(path, source events, stored sensor size)`` for one format at a time."""
    name, writer, size = WRITERS[request.param]
    path = tmp_path / name
    writer(path, events)
    return path, events, size
