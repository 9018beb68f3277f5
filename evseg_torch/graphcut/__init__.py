"""Multi-label graph cuts: α-expansion with Potts smoothness, label costs and an outlier label."""

from evseg_torch.graphcut.alpha_expansion import (
    ExpansionResult,
    GraphCutError,
    PottsGraph,
    alpha_expansion,
    labeling_energy,
    potts_graph,
)

__all__ = [
    "ExpansionResult",
    "GraphCutError",
    "PottsGraph",
    "alpha_expansion",
    "labeling_energy",
    "potts_graph",
]
