"""Events as torch tensors: one window, padded batches of windows."""

import numpy as np
import pytest
import torch

from evseg_torch.errors import EventFormatError
from evseg_torch.events import EventBatch, as_events, batch_windows, to_torch


def test_to_torch_relative_times_keep_precision(device, dtype):
    ev = as_events(np.array([[1_600_000_000.0, 1, 2, 1], [1_600_000_000.000001, 3, 4, 0]]))
    batch = to_torch(ev, device=device, dtype=dtype)
    assert batch.xy.shape == (2, 2) and batch.xy.dtype == dtype and batch.xy.device.type == device.type
    torch.testing.assert_close(batch.t.cpu(), torch.tensor([0.0, 1e-6], dtype=dtype))
    assert batch.p.tolist() == [1.0, -1.0]
    assert len(batch) == 2
    assert to_torch(ev, t_ref_us=int(ev["t"][1])).t[0].item() == pytest.approx(-1e-6)


class TestEventBatchBatches:
    def _windows(self):
        rng = np.random.default_rng(0)
        return [
            EventBatch(
                torch.as_tensor(rng.uniform(0, 20, (n, 2)), dtype=torch.float32),
                torch.linspace(0, 0.01, n),
                torch.as_tensor(rng.choice([-1.0, 1.0], n), dtype=torch.float32),
            )
            for n in (5, 2, 7)
        ]

    def test_batch_then_unbatch_gives_the_windows_back(self):
        windows = self._windows()
        batch = batch_windows(windows)
        assert batch.is_batched and len(batch) == 3
        assert batch.xy.shape == (3, 7, 2) and batch.lengths.tolist() == [5, 2, 7]
        for window, back in zip(windows, batch.unbatch(), strict=True):
            for field in ("xy", "t", "p"):
                assert getattr(back, field).equal(getattr(window, field))

    def test_padding_is_zero_and_masked(self):
        batch = batch_windows(self._windows())
        assert batch.mask.sum(dim=1).tolist() == [5, 2, 7]
        padding = ~batch.mask
        assert not batch.p[padding].any() and not batch.xy[padding].any() and not batch.t[padding].any()

    def test_one_window_is_not_a_batch(self):
        window = self._windows()[0]
        assert not window.is_batched and bool(window.mask.all()) and len(window) == 5
        with pytest.raises(EventFormatError, match="padded batch"):
            window.unbatch()

    def test_replace_swaps_a_field(self):
        window = self._windows()[0]
        shifted = window._replace(t=window.t + 1.0)
        assert isinstance(shifted, EventBatch) and len(shifted) == 5 and shifted.xy is window.xy
        torch.testing.assert_close(shifted.t, window.t + 1.0)
        with pytest.raises(TypeError, match="4 fields"):
            EventBatch._make([window.xy, window.t])

    def test_to_casts_events_but_keeps_integer_lengths(self):
        batch = batch_windows(self._windows()).to(torch.float64)
        assert batch.xy.dtype == torch.float64 and batch.lengths.dtype == torch.int64

    def test_bad_windows_are_named(self):
        windows = self._windows()
        with pytest.raises(EventFormatError, match="at least one"):
            batch_windows([])
        with pytest.raises(EventFormatError, match="window 1 is not"):
            batch_windows([windows[0], batch_windows(windows)])
        bad = EventBatch(windows[1].xy, windows[1].t, windows[1].p[:1])
        with pytest.raises(EventFormatError, match="window 1 must have"):
            batch_windows([windows[0], bad])
