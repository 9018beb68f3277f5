"""Objects in level two: object groups, supports and splits, and the segmenter's object phase."""

import numpy as np
import pytest
import torch

from evseg_torch.events import to_torch
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.objects import (
    cluster_groups,
    coverage,
    object_groups,
    spans_view,
    split_objects,
    support_cost,
    support_mask,
)
from evseg_torch.synthetic import make_scene

SIZE = (180, 240)


def _blob(rng, centre, n, half=6):
    """``n`` points filling a square of side ``2 half`` about ``centre``."""
    return np.asarray(centre, dtype=np.float64) + rng.uniform(-half, half, (n, 2))


def _groups(xy, polarity, **kwargs):
    return object_groups(
        xy, polarity, SIZE, radius=kwargs.get("radius", 5), min_events=kwargs.get("min_events", 100)
    )


class TestObjectGroups:
    def test_two_objects_apart_are_two_groups(self):
        rng = np.random.default_rng(0)
        xy = np.concatenate([_blob(rng, (60, 90), 400), _blob(rng, (180, 90), 300)])
        polarity = rng.choice([-1, 1], len(xy))
        group, n_groups = _groups(xy, polarity)
        assert n_groups == 2
        assert len(np.unique(group[:400])) == 1 and len(np.unique(group[400:])) == 1
        assert group[0] != group[-1]

    def test_near_parts_are_one_group(self):
        rng = np.random.default_rng(1)
        xy = np.concatenate([_blob(rng, (100, 90), 400), _blob(rng, (118, 90), 400)])  # 6 px apart
        assert _groups(xy, rng.choice([-1, 1], len(xy)))[1] == 1

    def test_edge_strips_of_opposite_signs_are_one_object(self):
        # A textureless object's leading edge fires one sign and its trailing edge the other, 40 px apart.
        rng = np.random.default_rng(2)
        leading = np.column_stack([rng.uniform(139, 141, 300), rng.uniform(50, 130, 300)])
        trailing = np.column_stack([rng.uniform(99, 101, 300), rng.uniform(50, 130, 300)])
        xy = np.concatenate([leading, trailing])
        polarity = np.repeat([1, -1], 300)
        group, n_groups = _groups(xy, polarity)
        assert n_groups == 1 and np.all(group == 0)

    def test_strips_of_one_sign_stay_together(self):
        # Strips without a partner of the other sign (a spurious model holding edges of two objects)
        # are never split into clusters of their own.
        rng = np.random.default_rng(3)
        xy = np.concatenate([_blob(rng, (60, 90), 300), _blob(rng, (180, 90), 300)])
        assert _groups(xy, np.ones(len(xy)))[1] == 1

    def test_a_strip_joins_its_object(self):
        rng = np.random.default_rng(4)
        xy = np.concatenate(
            [_blob(rng, (60, 90), 300), _blob(rng, (180, 90), 300), _blob(rng, (60, 140), 200)]
        )
        polarity = np.concatenate([rng.choice([-1, 1], 600), -np.ones(200)])
        group, n_groups = _groups(xy, polarity)
        assert n_groups == 2
        assert group[-1] == group[0]  # the strip joins the nearest object carrying the other sign

    def test_scattered_events_are_in_no_group(self):
        rng = np.random.default_rng(5)
        scattered = rng.uniform(0, 1, (150, 2)) * [239, 179]
        xy = np.concatenate([_blob(rng, (120, 90), 400), scattered])
        group, n_groups = _groups(xy, rng.choice([-1, 1], len(xy)))
        assert n_groups == 1
        assert np.mean(group[400:] == -1) > 0.9 and np.all(group[:400] == 0)

    def test_too_few_events_make_no_group(self):
        rng = np.random.default_rng(6)
        group, n_groups = _groups(_blob(rng, (120, 90), 50), np.ones(50))
        assert n_groups == 0 and np.all(group == -1)


def test_support_mask_is_the_grouped_pixels_dilated():
    xy = np.array([[10.0, 20.0], [200.0, 100.0]])
    mask = support_mask(xy, np.array([0, -1]), SIZE, radius=2)
    assert mask.shape == SIZE and mask[20, 10] and mask[22, 12] and not mask[23, 10]
    assert not mask[100, 200]  # an event in no group is no support
    assert support_mask(xy, np.array([-1, -1]), SIZE, radius=0)[100, 200]  # unless none has a group


def test_support_cost_charges_events_away_from_an_objects_groups():
    rng = np.random.default_rng(8)
    background = rng.uniform(0, 1, (3000, 2)) * [239, 179]
    blob = _blob(rng, (120, 90), 400)
    xy = np.concatenate([background, blob])
    labels = np.repeat([0, 1], [3000, 400])
    warped = np.stack([xy, xy])  # both models leave the events where they are
    polarity = rng.choice([-1, 1], len(xy))
    groups = cluster_groups(warped, labels, polarity, xy.astype(np.int64), SIZE, radius=5, min_events=100)
    assert list(groups) == [1]  # the background (the largest cluster) has none
    cost = support_cost(warped, groups, labels, [], SIZE, cost=64.0, radius=6)
    assert np.all(cost[:, 0] == 0) and np.all(cost[3000:, 1] == 0)
    far = np.linalg.norm(background - [120, 90], axis=1) > 20
    assert np.all(cost[:3000][far, 1] == 64.0)


def test_the_background_is_the_cluster_that_spreads_widest():
    # Dense objects may hold more events than a sparse background: the background is the cluster whose
    # events cover the view, and the objects' cluster is the one that gets groups (its support and split).
    rng = np.random.default_rng(9)
    background = rng.uniform(0, 1, (1500, 2)) * [239, 179]
    objects = np.concatenate([_blob(rng, (60, 90), 1500), _blob(rng, (180, 90), 1500)])
    xy = np.concatenate([background, objects])
    labels = np.repeat([0, 1], [1500, 3000])
    polarity = rng.choice([-1, 1], len(xy))
    groups = cluster_groups(
        np.stack([xy, xy]), labels, polarity, xy.astype(np.int64), SIZE, radius=5, min_events=100
    )
    assert list(groups) == [1] and groups[1][1] == 2  # the objects' cluster: two groups, one per object
    assert coverage(background.astype(np.int64), SIZE) > 0.35 > coverage(objects.astype(np.int64), SIZE)


def test_split_objects_gives_each_group_a_label():
    labels = np.array([0, 1, 1, 1, 1, 2, 2])
    groups = {1: (np.array([0, 1, 1, -1]), 2), 2: (np.array([0, 0]), 1)}
    split, parent = split_objects(labels, groups)
    np.testing.assert_array_equal(split, [0, 3, 1, 1, 1, 2, 2])  # the largest group keeps label 1
    np.testing.assert_array_equal(parent, [0, 1, 2, 1])
    np.testing.assert_array_equal(labels, [0, 1, 1, 1, 1, 2, 2])  # the input is not modified


def test_spans_view_tells_a_background_from_two_objects():
    rng = np.random.default_rng(7)
    background = (rng.uniform(0, 1, (1500, 2)) * [239, 179]).astype(np.int64)
    objects = np.concatenate([_blob(rng, (40, 90), 500, 15), _blob(rng, (200, 90), 500, 15)]).astype(np.int64)
    assert spans_view(background, SIZE) and not spans_view(objects, SIZE)


def _square(cx, cy, half):
    return np.array(
        [[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]]
    )


def _clusters_of_layers(scene, pool, **settings):
    """For each true layer, the fraction of its events in each cluster, :math:`(L, K)`."""
    segmenter = GraphCutContrastSegmenter("translation", SIZE, **settings)
    labels = segmenter(
        to_torch(scene.events), torch.as_tensor(np.stack(pool), dtype=torch.float32)
    ).labels.numpy()
    shares = np.stack(
        [
            np.bincount(labels[scene.labels == layer], minlength=labels.max() + 1)
            for layer in (0, 1, 2)[: len(scene.motions)]
        ]
    )
    return shares / shares.sum(axis=1, keepdims=True)


BACKGROUND, OBJECT = np.array([60.0, -20.0]), np.array([-250.0, 150.0])


@pytest.fixture(scope="module")
def twins():
    """Two textured squares 84 px apart with one motion, on a denser background with another."""
    return make_scene(
        SIZE,
        0.03,
        2,
        motion_model="translation",
        layer_params=[BACKGROUND, OBJECT, OBJECT],
        object_shapes=[_square(60, 90, 18), _square(180, 90, 18)],
        background_density=6.0,
        rng=1,
    )


def test_two_objects_that_move_alike_are_two_clusters(twins):
    shares = _clusters_of_layers(twins, [BACKGROUND, OBJECT])
    owners = shares.argmax(axis=1)
    assert len(set(owners.tolist())) == 3, shares  # background and each object: three clusters
    assert np.all(shares.max(axis=1) > 0.85), shares


def test_the_paper_reading_keeps_one_cluster_per_motion(twins):
    shares = _clusters_of_layers(twins, [BACKGROUND, OBJECT], objects=False)
    assert shares[1].argmax() == shares[2].argmax() != shares[0].argmax(), shares


def test_a_textureless_object_is_one_cluster():
    # Only the outline of a 40 x 80 px rectangle fires: moving sideways, its leading and trailing edges
    # are two strips of opposite signs 40 px apart.
    motion = np.array([300.0, 0.0])
    scene = make_scene(
        SIZE,
        0.03,
        1,
        motion_model="translation",
        layer_params=[BACKGROUND, motion],
        object_shapes=[np.array([[100, 50], [140, 50], [140, 130], [100, 130]])],
        object_texture_contrast=0.0,
        background_density=6.0,
        rng=2,
    )
    shares = _clusters_of_layers(scene, [BACKGROUND, motion])
    assert shares[1].max() > 0.95 and shares[1].argmax() != shares[0].argmax(), shares


def test_the_result_says_which_objects_share_a_motion(twins):
    from evseg_torch.config import SegmenterConfig, replace_config
    from evseg_torch.pipeline import CascadedSegmenter

    config = replace_config(SegmenterConfig(), motion_model="translation", initial_models="replace")
    result = CascadedSegmenter(SIZE, config)(twins.events, initial_models=np.stack([BACKGROUND, OBJECT]))
    owners = [np.bincount(result.labels[twins.labels == layer]).argmax() for layer in (0, 1, 2)]
    assert len(set(owners)) == 3
    assert (
        result.shared_motion[owners[1]] == result.shared_motion[owners[2]] != result.shared_motion[owners[0]]
    )
    ids = result.object_ids[owners[1:]].tolist()
    assert len(set(ids)) == 2 and 0 not in ids  # two objects, two ids, neither the background's
