"""Level one (NumPy): feature correspondences and their clustering by Progressive-X.

The Progressive-X parts never import torch; the features (``extract_correspondences`` and friends) use
kornia's corner response and are loaded on first use.
"""

from evseg_torch.level_one.gc_ransac import gc_ransac, graph_cut_inliers
from evseg_torch.level_one.neighborhood import neighborhood_graph
from evseg_torch.level_one.progressive_x import OUTLIER, ProgressiveXResult, pearl, progressive_x

_FEATURES = {
    "Correspondences",
    "Tracks",
    "detect_corners",
    "event_image",
    "extract_correspondences",
    "guided_tracks",
    "track_features",
}


def __getattr__(name: str):
    if name in _FEATURES:
        from evseg_torch.level_one import features

        return getattr(features, name)
    raise AttributeError(f"module 'evseg_torch.level_one' has no attribute {name!r}")


__all__ = [
    "OUTLIER",
    "Correspondences",
    "ProgressiveXResult",
    "Tracks",
    "detect_corners",
    "event_image",
    "extract_correspondences",
    "gc_ransac",
    "graph_cut_inliers",
    "guided_tracks",
    "neighborhood_graph",
    "pearl",
    "progressive_x",
    "track_features",
]
