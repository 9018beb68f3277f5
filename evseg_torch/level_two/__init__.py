"""Level two (torch): images of warped events, contrast maximisation and graph-cut event clustering."""

from evseg_torch.level_two.descent.segmenter import (
    GraphCutContrastSegmenter,
    LevelTwoResult,
)
from evseg_torch.level_two.energy.data_term import DataCost, data_cost, sample_bilinear
from evseg_torch.level_two.energy.graph import event_graph, pixel_adjacency, site_graph
from evseg_torch.level_two.image.splat import ImageOfWarpedEvents, splat_events, warped_iwe
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.level_two.objectives.contrast import (
    CONTRAST_OBJECTIVES,
    ContrastLoss,
    contrast_loss,
    image_variance,
    normalized_variance,
    padded_contrast_loss,
)
from evseg_torch.level_two.objectives.multi_model import MultiModelContrastLoss, multi_model_contrast_loss
from evseg_torch.level_two.solver.cmax import ContrastMaximization

__all__ = [
    "CONTRAST_OBJECTIVES",
    "ContrastLoss",
    "ContrastMaximization",
    "DataCost",
    "GraphCutContrastSegmenter",
    "ImageOfWarpedEvents",
    "LevelTwoResult",
    "MultiModelContrastLoss",
    "contrast_loss",
    "data_cost",
    "event_graph",
    "image_variance",
    "multi_model_contrast_loss",
    "normalized_variance",
    "padded_contrast_loss",
    "pixel_adjacency",
    "sample_bilinear",
    "site_graph",
    "splat_events",
    "warp_events",
    "warped_iwe",
]
