"""The label cost of a window: EMSGC's MDL term, scaled with dense windows (beyond the paper)."""

from __future__ import annotations

__all__ = ["label_cost"]


def label_cost(n_events: int, lambda_label: float, label_cost_events: float | None) -> float:
    """What each model in use costs a window of ``n_events``: ``lambda_label``, times
    ``n_events / label_cost_events`` in windows of more than ``label_cost_events`` events (``None``:
    ``lambda_label`` whatever the window, as in EMSGC).

    The data cost that a spurious model saves grows with the events it takes, so dense windows need a
    dearer label; sparse ones keep ``lambda_label``, which a small object's sharper model can pay.

    Examples:
        >>> label_cost(5000, 6000.0, 15000.0), label_cost(30000, 6000.0, 15000.0)
        (6000.0, 12000.0)
    """
    if label_cost_events is None:
        return lambda_label
    return lambda_label * max(1.0, n_events / label_cost_events)
