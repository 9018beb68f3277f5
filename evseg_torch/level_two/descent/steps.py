"""The steps of level two's descent, and the one function that decides which comes next.

A window is labelled, then its clusters' models are refitted and it is labelled again, until the
labels settle (EMSGC's block-coordinate descent). Beyond the paper, a settled window then takes up to
``discovery_rounds`` discovery steps (each followed by a labelling of the pool with the proposals) and
the object phase: one *support* step (the support term joins the data costs; a labelling follows when
some event lies outside its own cluster's support) and up to ``object_splits`` *split* steps (clusters
of separate objects split, refitted and labelled again). Every step's outcome is written into the
window's :class:`~evseg_torch.level_two.descent.state.WindowState`; :func:`next_step` reads it.

A discovery step that proposes nothing ends the window: its labelling stands as the one that every
region of the round was judged against, and the object phase does not run (a window with
``discovery_rounds`` 0 goes from its settled labelling straight to the object phase).
"""

from __future__ import annotations

from enum import Enum
from typing import Protocol

__all__ = ["Step", "next_step"]


class Step(Enum):
    """A step of level two's descent (module docstring)."""

    LABEL = "label"  # α-expansion of the current data costs (EMSGC's labelling)
    REFIT = "refit"  # contrast maximisation of every cluster's model on its events (EMSGC's refit)
    PROPOSE = "propose"  # discovery: models proposed for candidate regions
    SUPPORT = "support"  # the object phase's support term added to the data costs
    SPLIT = "split"  # clusters of separate objects split into one cluster each
    STOP = "stop"  # the window is done


class Outcomes(Protocol):
    """What :func:`next_step` reads of a window
    (a :class:`~evseg_torch.level_two.descent.state.WindowState`)."""

    last: Step
    settled: bool
    proposed: bool
    outside_support: bool
    split_made: bool
    discoveries_left: int
    objects_on: bool
    splits_left: int


def next_step(state: Outcomes, objects: bool) -> Step:
    """The step a window takes after its last one (module docstring).

    Args:
        state: the window, its last step and that step's outcome.
        objects: whether the object phase runs (``level_two.objects``).

    Returns:
        The next step; every step but :attr:`Step.STOP` is eventually followed by a labelling.
    """
    last = state.last
    if last is Step.REFIT:
        return Step.LABEL
    if last is Step.PROPOSE:
        return Step.LABEL if state.proposed else Step.STOP
    if last is Step.SPLIT:
        return Step.REFIT if state.split_made else Step.STOP
    if last is Step.SUPPORT and state.outside_support:
        return Step.LABEL
    if last is Step.LABEL:
        if not state.settled:
            return Step.REFIT
        if state.discoveries_left > 0:
            return Step.PROPOSE
        if objects and not state.objects_on:
            return Step.SUPPORT
    if objects and state.splits_left > 0:
        return Step.SPLIT
    return Step.STOP
