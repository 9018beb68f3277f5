"""Helpers that lay the windows of a batch out as shared tensors: memberships, padding, chunks."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.events import EventBatch
from evseg_torch.level_two.descent.state import WindowState

__all__ = ["chunks", "memberships", "padded_pools", "padded_rows", "select_windows", "subsample"]


def memberships(labels: Tensor, n_clusters: int, dtype: torch.dtype) -> Tensor:
    """One-hot memberships :math:`(..., K, N)` of labels :math:`(..., N)`; label -1 (padding) is in none."""
    return (labels[..., None, :] == torch.arange(n_clusters, device=labels.device)[:, None]).to(dtype)


def subsample(weights: Tensor, max_events: int) -> Tensor:
    """Keep every s-th member of each cluster (in event order), s chosen so that at most ``max_events`` stay.

    Args:
        weights: one-hot memberships :math:`(..., K, N)`.
    """
    counts = weights.sum(dim=-1, keepdim=True)
    stride = torch.ceil(counts / max_events).clamp_min(1)
    rank = torch.cumsum(weights, dim=-1) - 1
    return weights * (torch.remainder(rank, stride) == 0)


def chunks(sizes: Sequence[int], budget: int | None) -> list[list[int]]:
    """Consecutive indices of ``sizes`` in chunks whose sizes add up to at most ``budget`` (each chunk
    holds one at least); one chunk of all for ``budget`` ``None``."""
    chunks, total = [[]], 0
    for index, size in enumerate(sizes):
        total += size
        if chunks[-1] and budget is not None and total > budget:
            chunks.append([])
            total = size
        chunks[-1].append(index)
    return chunks


def select_windows(batch: EventBatch, states: Sequence[WindowState]) -> EventBatch:
    """The windows of ``states`` from the padded batch (itself when it holds just them), padded to the
    longest of them."""
    rows = [state.index for state in states]
    if rows == list(range(len(batch))):
        return batch
    index = torch.as_tensor(rows, device=batch.xy.device)
    longest = max(len(state.events) for state in states)
    xy, t, p, lengths = (field[index] for field in batch)
    return EventBatch(xy[:, :longest], t[:, :longest], p[:, :longest], lengths)


def padded_rows(rows: Sequence[np.ndarray], length: int, device: torch.device) -> Tensor:
    """Integer rows :math:`(n_b,)` as one int64 tensor :math:`(B, L)`, ``L = length``, padded with -1,
    moved to ``device`` in one copy."""
    padded = np.full((len(rows), length), -1, dtype=np.int64)
    for index, row in enumerate(rows):
        padded[index, : len(row)] = row
    return torch.as_tensor(padded, device=device)


def padded_pools(pools: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """Pools :math:`(K_b, P)` as one tensor :math:`(B, K, P)` padded with zeros, and which models are
    real, bool :math:`(B, K)`."""
    params = nn.utils.rnn.pad_sequence(list(pools), batch_first=True)
    counts = torch.tensor([len(pool) for pool in pools], device=params.device)
    return params, torch.arange(params.shape[1], device=params.device) < counts[:, None]
