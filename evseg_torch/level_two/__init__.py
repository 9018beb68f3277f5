"""Level two (PyTorch): EMSGC's graph-cut clustering of events with contrast-maximisation refits.

Given a window's events and a pool of motion models, level two labels every event with a model and
refits each cluster's model, minimising EMSGC's energy (data term, Potts term, label cost). Its parts,
each a sub-package or module a reader can find by name:

* :mod:`~evseg_torch.level_two.image`: events warped by a motion, splatted and blurred into images of
  warped events (IWEs), and their variance;
* :mod:`~evseg_torch.level_two.objectives`: contrast losses of one motion per cluster or of soft
  assignments, differentiable for learning;
* :mod:`~evseg_torch.level_two.solver`: contrast maximisation of every cluster's motion as one batched
  L-BFGS (or Adam) problem;
* :mod:`~evseg_torch.level_two.energy`: the data term, the spatio-temporal event graph and the label cost;
* :mod:`~evseg_torch.level_two.descent`: the segmenter, a driver of each window's steps, and the one
  function that decides them;
* :mod:`~evseg_torch.level_two.discovery` and :mod:`~evseg_torch.level_two.objects`: proposals of missed
  motions and one cluster per object (both beyond the paper).

The compiled forms of some steps are in :mod:`evseg_torch.kernels`, chosen by :mod:`evseg_torch.backend`.
Level two never imports level one; :mod:`evseg_torch.pipeline` joins them.
"""

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
