"""Multi-label graph cuts: α-expansion with Potts smoothness, label costs and an outlier label.

:mod:`~evseg_torch.graphcut.problem` defines the labelling problem and its energy,
:mod:`~evseg_torch.graphcut.alpha_expansion` minimises it by expansion moves on PyMaxflow.
"""

from evseg_torch.graphcut.alpha_expansion import ExpansionResult, alpha_expansion
from evseg_torch.graphcut.problem import GraphCutError, PottsGraph, labeling_energy, potts_graph

__all__ = [
    "ExpansionResult",
    "GraphCutError",
    "PottsGraph",
    "alpha_expansion",
    "labeling_energy",
    "potts_graph",
]
