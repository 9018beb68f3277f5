import numpy as np

from evseg_torch.motion import make_motion_model
from evseg_torch.motion.shared import SHARED_MOTION_PX, shared_motion_groups

SIZE = (180, 240)
MOTION = make_motion_model("translation", SIZE)


def test_clusters_moving_alike_share_a_motion():
    boxes = np.array([[np.nan] * 4, [10, 10, 10, 10], [60, 50, 10, 10], [90, 20, 10, 10]])
    # Clusters 0 and 2 differ by 50 px/s = 0.5 px over 10 ms; cluster 3 by 300 px/s = 3 px.
    models = np.array([[100, 0], [0, 500], [150, 0], [400, 0]], dtype=float)
    assert SHARED_MOTION_PX == 2.0
    assert shared_motion_groups(models, boxes, 0.01, MOTION, SIZE).tolist() == [0, 1, 0, 3]
    assert shared_motion_groups(models, boxes, 0.01, MOTION, SIZE, tolerance_px=3.5).tolist() == [0, 1, 0, 0]


def test_an_affine_difference_peaks_at_the_corners_of_the_common_box():
    affine = make_motion_model("affine4", SIZE)
    boxes = np.array([[0, 0, 239, 179], [100, 80, 10, 10]], dtype=float)
    # The same translation, one with a rotation rate of 1 rad/s: at the far corners of the whole view it
    # moves points ~150 px/s apart, 1.5 px over 10 ms, 4.5 px over 30 ms.
    models = np.array([[50, 0, 0, 0], [50, 0, 0, 1.0]])
    assert shared_motion_groups(models, boxes, 0.01, affine, SIZE).tolist() == [0, 0]
    assert shared_motion_groups(models, boxes, 0.03, affine, SIZE).tolist() == [0, 1]
