"""Correspondences of known motions for level one's tests: a background, objects in discs, outliers."""

import numpy as np

from evseg_torch.motion import Affine4, Translation

SENSOR = (180, 240)
# Object centres (x, y) and motions: the background first, then up to three objects. Per-second
# rates over a 30 ms window: the objects' displacements differ from the background's by >= 5 px.
CENTRES = np.array([[55.0, 50.0], [185.0, 60.0], [120.0, 135.0]])
AFFINE = np.array(
    [[60.0, -30.0, 0.3, 0.2], [-250.0, 60.0, 0.5, -0.4], [180.0, 220.0, -0.3, 0.3], [40.0, -300.0, 0.2, 0.6]]
)
DT = 0.03


def make_scene(
    rng,
    name="affine4",
    n_motions=3,
    *,
    n_background=120,
    n_object=45,
    outlier_ratio=0.3,
    noise=0.3,
    radius=28.0,
    params=None,
    centres=CENTRES,
    dt=DT,
):
    """Correspondences of a background spread over the image and objects in their own discs.

    Outliers are uniform positions with a uniform displacement in ``[-10, 10]^2`` px. Returns
    ``(model, src, dst, dt, ground-truth labels with -1 for outliers, params)``.
    """
    rng = np.random.default_rng(rng)
    model = Affine4(SENSOR) if name == "affine4" else Translation(SENSOR)
    if params is None:
        params = AFFINE[:n_motions] if name == "affine4" else AFFINE[:n_motions, :2]
    height, width = SENSOR
    background = rng.uniform([0, 0], [width, height], (6 * n_background, 2))
    occluded = np.zeros(len(background), dtype=bool)
    for centre in centres[: n_motions - 1]:
        occluded |= np.linalg.norm(background - centre, axis=1) < radius + 5
    points, truth = [background[~occluded][:n_background]], [np.zeros(n_background, dtype=np.int64)]
    for k, centre in enumerate(centres[: n_motions - 1]):
        angle = rng.uniform(0, 2 * np.pi, n_object)
        distance = radius * np.sqrt(rng.uniform(0, 1, n_object))
        points.append(centre + distance[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1))
        truth.append(np.full(n_object, k + 1))
    src, truth = np.concatenate(points), np.concatenate(truth)
    dst = np.empty_like(src)
    for k in range(n_motions):
        dst[truth == k] = model.predict(src[truth == k], dt, params[k])
    dst += rng.normal(0, noise, dst.shape)
    n_outliers = round(outlier_ratio * len(src) / (1 - outlier_ratio))
    outlier_src = rng.uniform([0, 0], [width, height], (n_outliers, 2))
    src = np.concatenate([src, outlier_src])
    dst = np.concatenate([dst, outlier_src + rng.uniform(-10, 10, (n_outliers, 2))])
    truth = np.concatenate([truth, np.full(n_outliers, -1)])
    order = rng.permutation(len(src))
    return model, src[order], dst[order], np.full(len(src), dt), truth[order], params


# Level one tested alone: an instance needs 10 tracks (pyprogressivex's minimum). The pipeline's default,
# the config's 4, leaves weak models to level two's label cost.
ALONE = {"minimum_point_number": 10}
