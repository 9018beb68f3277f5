import numpy as np
import pytest

from evseg_torch.errors import ShapeError
from evseg_torch.evaluation.metrics import (
    box_intersection,
    box_iou,
    box_of_points,
    boxes_nested,
    convex_hull_mask,
    event_iou,
    event_pixel_iou,
    labelling_accuracy,
    mask_iou,
    match_clusters,
    mean_iou,
    object_outcomes,
    per_object_iou,
    success_rate,
)
from evseg_torch.events import EVENT_DTYPE


class TestEventMetrics:
    def test_permuted_labels_are_perfect(self):
        gt = np.array([0, 0, 0, 1, 1, 2, -1])
        pred = np.array([5, 5, 5, 3, 3, 0, 0])
        assert match_clusters(pred, gt) == {5: 0, 3: 1, 0: 2}
        assert labelling_accuracy(pred, gt) == 1.0
        assert per_object_iou(pred, gt) == {1: 1.0, 2: 1.0}

    def test_hand_computed_case(self):
        gt = np.array([0, 0, 0, 0, 1, 1, 1, 1])
        pred = np.array([0, 0, 0, 1, 1, 1, 1, 0])
        # Matching 0->0, 1->1: events 3 and 7 are wrong.
        assert labelling_accuracy(pred, gt) == pytest.approx(6 / 8)
        # Object 1: gt {4,5,6,7}, cluster 1 {3,4,5,6}: intersection 3, union 5.
        assert per_object_iou(pred, gt) == {1: pytest.approx(3 / 5)}

    def test_merged_clusters_lose_the_unmatched_layer(self):
        gt = np.array([0, 0, 1, 1])
        pred = np.zeros(4, dtype=int)
        assert labelling_accuracy(pred, gt) == 0.5
        assert per_object_iou(pred, gt) == {1: 0.0}

    def test_unassigned_events_count_as_wrong(self):
        assert labelling_accuracy(np.array([-1, 0]), np.array([0, 0])) == 0.5

    def test_shape_error(self):
        with pytest.raises(ShapeError, match="equal length"):
            labelling_accuracy(np.zeros(3), np.zeros(4))


class TestBoxes:
    def test_iou_hand_computed(self):
        a = np.array([0.0, 0, 10, 10])
        b = np.array([5.0, 5, 10, 10])
        assert box_intersection(a, b) == 25
        assert box_iou(a, b) == pytest.approx(25 / 175)
        assert box_iou(a, a) == 1.0
        assert box_iou(a, np.array([20.0, 20, 1, 1])) == 0.0
        assert box_iou(a, np.full(4, np.nan)) == 0.0

    def test_broadcasting(self):
        boxes = np.array([[0.0, 0, 10, 10], [0, 0, 5, 10]])
        np.testing.assert_allclose(box_iou(boxes, np.array([0.0, 0, 10, 10])), [1.0, 0.5])

    def test_nested_hand_computed(self):
        gt = np.array([0.0, 0, 10, 10])
        # 6 x 6 inside: intersection 36 covers all of the smaller box, areas 100 / 36 = 2.8 <= 4.
        assert boxes_nested(np.array([2.0, 2, 6, 6]), gt)
        assert boxes_nested(gt, np.array([2.0, 2, 6, 6]))  # symmetric
        # 4 x 4 inside: covered, but 100 / 16 = 6.25 > 4.
        assert not boxes_nested(np.array([2.0, 2, 4, 4]), gt)
        # 5 x 5 across the corner, 2 x 2 inside: 4 / 25 of the smaller box.
        assert not boxes_nested(np.array([8.0, 8, 5, 5]), gt)
        # 10 x 5 at half height: IoU 0.25 yet covers 30 / 50 of the smaller box, areas 2x.
        shifted = np.array([0.0, 2, 10, 5])
        assert box_iou(shifted, np.array([0.0, 4, 10, 10])) < 0.5
        assert boxes_nested(shifted, np.array([0.0, 4, 10, 10]))

    def test_nested_limits_and_empty_boxes(self):
        gt = np.array([0.0, 0, 10, 10])
        half = np.array([0.0, 0, 5, 10])  # covers all of itself; areas exactly 2x
        assert boxes_nested(half, gt) and not boxes_nested(half, gt, max_area_ratio=1.9)
        assert not boxes_nested(np.array([5.0, 0, 5, 10]), np.array([0.0, 0, 10, 10]), min_cover=1.0)
        assert not boxes_nested(np.array([0.0, 0, 0, 10]), np.array([0.0, 0, 0, 10]))
        assert not boxes_nested(np.full(4, np.nan), gt)
        np.testing.assert_array_equal(
            boxes_nested(np.array([[2.0, 2, 6, 6], [2, 2, 4, 4]]), gt), [True, False]
        )

    def test_box_of_points(self):
        np.testing.assert_allclose(box_of_points(np.array([[1.0, 2], [4, 8], [2, 3]])), [1, 2, 3, 6])
        assert np.all(np.isnan(box_of_points(np.zeros((0, 2)))))


class TestMasks:
    def test_convex_hull_of_square_corners(self):
        mask = convex_hull_mask(np.array([[2.0, 2], [6, 2], [6, 5], [2, 5]]), (10, 10))
        assert mask.sum() == 5 * 4 and mask[3, 4] and not mask[1, 1]

    def test_mask_iou(self):
        a = np.zeros((4, 4), bool)
        b = np.zeros((4, 4), bool)
        a[:2] = True
        b[1:3] = True
        assert mask_iou(a, b) == pytest.approx(4 / 12)
        assert np.isnan(mask_iou(np.zeros((2, 2)), np.zeros((2, 2))))
        with pytest.raises(ShapeError):
            mask_iou(a, np.zeros((3, 3)))


class TestLearnedMaskerMetrics:
    """Hand-computed values on 2 x 3 masks (event_suppression's definitions)."""

    PRED = np.array([[1, 1, 0], [0, 0, 0]], dtype=bool)
    GT = np.array([[1, 0, 0], [0, 0, 1]], dtype=bool)

    def test_mean_iou(self):
        # Dynamic: 1 shared of 3 pixels; background: 3 shared ((0,2), (1,0), (1,1)) of 5.
        assert mean_iou(self.PRED, self.GT) == pytest.approx((1 / 3 + 3 / 5) / 2)
        assert mean_iou(self.PRED, self.PRED) == 1.0

    def test_mean_iou_leaves_out_a_class_absent_from_both(self):
        empty = np.zeros((2, 3), dtype=bool)
        assert mean_iou(empty, empty) == 1.0  # the dynamic IoU is undefined, the background one is 1
        assert mean_iou(self.PRED, empty) == pytest.approx((0 + 4 / 6) / 2)

    def test_event_pixel_iou(self):
        events = np.array([[1, 0, 1], [0, 0, 1]], dtype=bool)
        # On event pixels: predicted {(0,0)}, ground truth {(0,0), (1,2)}.
        assert event_pixel_iou(self.PRED, self.GT, events) == 0.5
        assert np.isnan(event_pixel_iou(self.PRED, self.GT, np.zeros((2, 3), dtype=bool)))

    def test_success_rate(self):
        assert success_rate([0.5, 0.49, float("nan"), 0.9]) == pytest.approx(2 / 3)
        assert success_rate([0.5, 0.49], threshold=0.4) == 1.0
        assert np.isnan(success_rate([float("nan")])) and np.isnan(success_rate([]))

    def test_event_iou_counts_events_not_pixels(self):
        events = np.zeros(5, dtype=EVENT_DTYPE)
        # (x, y): two events on object pixel (0, 0), one on object pixel (2, 1), two off the object.
        events["x"], events["y"] = [0, 0, 2, 1, 2], [0, 0, 1, 0, 0]
        is_dynamic = np.array([True, True, False, True, False])
        # Predicted {0, 1, 3}, on the object {0, 1, 2}: 2 shared of 4.
        assert event_iou(is_dynamic, events, self.GT) == 0.5
        assert np.isnan(event_iou(np.zeros(2, bool), events[3:], self.GT))
        with pytest.raises(ShapeError):
            event_iou(is_dynamic[:2], events, self.GT)


class TestObjectOutcomes:
    """Why each object is missed: read from the cluster that holds most of its events."""

    # Layers: 0 background (10 events), objects 1..5 (10 events each); noise -1 left out.
    gt = np.repeat([0, 1, 2, 3, 4, 5], 10)

    def outcomes(self, pred, detected=(False,) * 5):
        pred = np.asarray(pred)
        dynamic = pred != 0  # cluster 0 is the background
        return object_outcomes(pred, self.gt, list(detected), dynamic)

    def test_each_reason(self):
        pred = np.concatenate(
            [
                np.zeros(10),  # background
                np.zeros(10),  # object 1 in the background's cluster
                np.full(10, 2),  # objects 2 and 3 share cluster 2
                np.full(10, 2),
                np.r_[np.full(5, 4), np.full(5, 5)],  # object 4 split over clusters 4 and 5
                np.r_[np.full(9, 6), -np.ones(1)],  # object 5 its own cluster (box stretched, say)
            ]
        ).astype(int)
        assert self.outcomes(pred) == ("background", "merged", "merged", "split", "stretched")

    def test_detected_objects_and_unassigned_ones(self):
        pred = np.r_[np.zeros(10), np.full(10, 1), -np.ones(10), np.full(30, 3)].astype(int)
        outcomes = self.outcomes(pred, detected=(True, False, False, False, False))
        assert outcomes[:2] == ("detected", "unassigned")

    def test_noise_and_ignored_events_are_not_foreign(self):
        gt = np.r_[np.zeros(10), np.ones(10), -np.ones(10)].astype(int)
        pred = np.r_[np.zeros(10), np.ones(20)].astype(int)
        assert object_outcomes(pred, gt, [False], pred != 0) == ("stretched",)

    def test_one_flag_per_object(self):
        with pytest.raises(ShapeError):
            object_outcomes(np.zeros(60, int), self.gt, [False], np.zeros(60, bool))
