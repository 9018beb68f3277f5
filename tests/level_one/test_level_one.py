"""Features plus Progressive-X on synthetic event scenes: every moving object must get a model."""

import numpy as np

from evseg_torch.level_one.features import extract_correspondences
from evseg_torch.level_one.progressive_x import progressive_x
from evseg_torch.synthetic import make_scene
from tests.helpers.level_one import ALONE

SENSOR = (180, 240)
DURATION = 0.03
# Hand-held speeds as in EED and EV-IMO (make_scene's own defaults reach 1500 px/s on this sensor,
# beyond what Lucas-Kanade on 10 ms event images tracks: a documented limitation of level one).
SPEED_RANGE = (100.0, 600.0)
MIN_RELATIVE_SPEED = 150.0
MIN_AREA = 0.03  # every IMO covering at least 3 % of the image must be found
TOLERANCE = 1.5  # px, mean displacement error over the layer's pixels over the window


def layer_errors(scene, params) -> list[float]:
    """For the background and every object covering ``MIN_AREA``, the best model's error in px.

    The error of a model for a layer is the mean, over the layer's visible pixels at mid-window, of
    the distance between the displacements over the window that the model and the true motion give.
    """
    labels = scene.label_image_at(DURATION / 2)
    rows, cols = np.indices(labels.shape)
    errors = []
    for label, motion in enumerate(scene.motions):
        visible = labels == label
        if label > 0 and visible.mean() < MIN_AREA:
            continue
        xy = np.column_stack([cols[visible], rows[visible]]).astype(np.float64)
        if len(params) == 0:
            errors.append(np.inf)
            continue
        difference = motion.model.velocity(xy, params) - motion.model.velocity(xy, motion.params)[None]
        errors.append(float(np.linalg.norm(difference, axis=-1).mean(axis=1).min() * DURATION))
    return errors


def test_every_moving_object_found():
    """Ten scenes of a background and 1-3 objects in affine4 motion; at least nine fully found."""
    found, report = 0, []
    for seed in range(10):
        scene = make_scene(
            SENSOR,
            DURATION,
            1 + seed % 3,
            speed_range=SPEED_RANGE,
            min_relative_speed=MIN_RELATIVE_SPEED,
            rng=seed,
        )
        tracks = extract_correspondences(scene.events, SENSOR, t_ref=scene.t0_us)
        result = progressive_x(tracks.src, tracks.dst, tracks.dt, scene.motions[0].model, rng=seed, **ALONE)
        errors = layer_errors(scene, result.params)
        found += max(errors) < TOLERANCE
        report.append((seed, len(tracks), len(result.params), np.round(errors, 2).tolist()))
    assert found >= 9, report
