"""Timing of level one (features and Progressive-X) per 30 ms window, cold and with model reuse.

The paper (Table III, one i7-8700K thread) reports 110 ms per window for level one and 15 ms when the
previous window's models are reused. This script times :func:`extract_correspondences` and
:func:`progressive_x` separately and prints medians. Windows come from a *source*:

* ``scenes`` (default): consecutive windows of synthetic event scenes (:func:`make_scene`, 90 ms, a
  background and 1-3 objects at 100-600 px/s);
* ``eed``: consecutive windows of EED's ``occlusions`` recording (``--data`` points at it);
* ``tracks``: no events, 100-300 drawn tracks of 2-4 affine motions with 20-30% outliers (Prog-X only).

BLAS (hence also torch) is pinned to one thread before NumPy loads, as in the paper's single-thread
timing; small matrix products only lose to threading overhead. OpenCV's Lucas-Kanade, about three
quarters of the features' time, keeps OpenCV's own thread count unless ``--opencv-threads`` says
otherwise; the header line prints it.

Usage::

    python benchmarks/bench_level_one.py [--source scenes|eed|tracks] [--windows 24] [--repeats 3]
        [--opencv-threads N]
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
# Idle OpenMP workers sleep instead of spinning on the cores that timing needs.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import NamedTuple  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from evseg_torch.level_one.features import extract_correspondences  # noqa: E402
from evseg_torch.level_one.progressive_x import progressive_x  # noqa: E402
from evseg_torch.motion import Affine4, MotionModel  # noqa: E402

SENSOR_SIZE = (180, 240)  # EED's DAVIS240, (H, W)
WINDOW = 0.03  # s between the two event images whose features are matched
EED_OCCLUSIONS = Path("/work/shared/data/real/eed_occlusions")


class Window(NamedTuple):
    """One window: its events (``None`` for drawn tracks) or its correspondences; ``sequence`` changes
    when the scene (its motions) does, ``n_motions`` is 0 where unknown."""

    events: np.ndarray | None
    src: np.ndarray | None
    dst: np.ndarray | None
    dt: np.ndarray | None
    n_motions: int
    sequence: int


def scene_windows(model: MotionModel, n_windows: int, rng: np.random.Generator) -> Iterator[Window]:
    """Three consecutive 30 ms windows per synthetic scene of 90 ms."""
    from evseg_torch.synthetic import make_scene

    step = round(WINDOW * 1e6)
    for sequence in range((n_windows + 2) // 3):
        n_objects = int(rng.integers(1, 4))
        scene = make_scene(
            SENSOR_SIZE, 3 * WINDOW, n_objects, speed_range=(100.0, 600.0), min_relative_speed=150.0, rng=rng
        )
        for start in range(0, 3 * step, step):
            t = scene.events["t"] - scene.t0_us
            yield Window(
                scene.events[(t >= start) & (t < start + step)], None, None, None, n_objects + 1, sequence
            )


def eed_windows(model: MotionModel, n_windows: int, rng: np.random.Generator) -> Iterator[Window]:
    """Consecutive 30 ms windows of EED ``occlusions``, from 0.2 s (one sequence: the motions persist)."""
    from evseg_torch.evaluation.eed import load_eed_sequence

    events = load_eed_sequence(EED_OCCLUSIONS).events
    start, step = int(events["t"][0]) + 200_000, round(WINDOW * 1e6)
    for index in range(n_windows):
        window = events[(events["t"] >= start + index * step) & (events["t"] < start + (index + 1) * step)]
        if len(window) > 1:
            yield Window(window, None, None, None, 0, 0)


def synthetic_windows(
    model: MotionModel, n_windows: int, rng: np.random.Generator, windows_per_sequence: int = 4
) -> Iterator[Window]:
    """Windows of a background plus 1-3 objects, each object's tracks in its own disc.

    Within a sequence the motions stay (up to a small drift) and the tracks, noise and outliers are
    drawn anew, as between consecutive windows of a recording.
    """
    height, width = SENSOR_SIZE
    for index in range(n_windows):
        if index % windows_per_sequence == 0:
            n_motions = int(rng.integers(2, 5))
            # Motions at least 150 px/s (4.5 px per window) apart from each other.
            velocity = rng.uniform(-300, 300, (n_motions, 2))
            gaps = np.linalg.norm(velocity[:, None] - velocity[None], axis=-1) + 1e3 * np.eye(n_motions)
            while gaps.min() < 150:
                velocity = rng.uniform(-300, 300, (n_motions, 2))
                gaps = np.linalg.norm(velocity[:, None] - velocity[None], axis=-1) + 1e3 * np.eye(n_motions)
            params = np.concatenate([velocity, rng.uniform(-0.5, 0.5, (n_motions, 2))], axis=1)
            centres = np.array([[55.0, 50.0], [185.0, 60.0], [120.0, 135.0]])[rng.permutation(3)]
            radii = rng.uniform(20, 35, 3)
            n_tracks = int(rng.integers(100, 301))
            outlier_ratio = rng.uniform(0.2, 0.3)
        params = params + rng.normal(0, [2.0, 2.0, 0.01, 0.01], params.shape)
        n_inliers = round(n_tracks * (1 - outlier_ratio))
        n_object = [max(15, round(n_inliers * rng.uniform(0.1, 0.2))) for _ in range(n_motions - 1)]
        n_background = n_inliers - sum(n_object)
        points = rng.uniform([0, 0], [width, height], (8 * n_background, 2))
        hidden = np.zeros(len(points), dtype=bool)
        for centre, radius in zip(centres[: n_motions - 1], radii, strict=False):
            hidden |= np.linalg.norm(points - centre, axis=1) < radius
        src, labels = [points[~hidden][:n_background]], [np.zeros(n_background, dtype=np.int64)]
        for k, (count, centre, radius) in enumerate(zip(n_object, centres, radii, strict=False)):
            angle = rng.uniform(0, 2 * np.pi, count)
            distance = radius * np.sqrt(rng.uniform(0, 1, count))
            src.append(centre + distance[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1))
            labels.append(np.full(count, k + 1))
        src, labels = np.concatenate(src), np.concatenate(labels)
        dst = np.empty_like(src)
        for k in range(n_motions):
            dst[labels == k] = model.predict(src[labels == k], WINDOW, params[k])
        dst += rng.normal(0, 0.3, dst.shape)
        n_outliers = n_tracks - len(src)
        outliers = rng.uniform([0, 0], [width, height], (n_outliers, 2))
        src = np.concatenate([src, outliers])
        dst = np.concatenate([dst, outliers + rng.uniform(-10, 10, (n_outliers, 2))])
        yield Window(None, src, dst, np.full(len(src), WINDOW), n_motions, index // windows_per_sequence)


SOURCES = {"scenes": scene_windows, "eed": eed_windows, "tracks": synthetic_windows}


def best_of(repeats: int, function, *args, **kwargs):
    """Smallest wall time in ms over ``repeats`` calls, and the last result."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function(*args, **kwargs)
        times.append(1e3 * (time.perf_counter() - start))
    return min(times), result


def main() -> None:
    global EED_OCCLUSIONS
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=sorted(SOURCES), default="scenes")
    parser.add_argument("--windows", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats per window (best is kept)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=EED_OCCLUSIONS, help="EED occlusions folder")
    parser.add_argument("--opencv-threads", type=int, default=None, help="OpenCV threads (default: its own)")
    args = parser.parse_args()
    EED_OCCLUSIONS = args.data
    if args.opencv_threads is not None:
        cv2.setNumThreads(args.opencv_threads)

    model = Affine4(SENSOR_SIZE)
    windows = list(SOURCES[args.source](model, args.windows, np.random.default_rng(args.seed)))
    cold_features, reuse_features, cold_ms, reuse_ms, rows = [], [], [], [], []

    def features(window: Window, initial_models=None) -> tuple[float, Window]:
        """Time the window's features (guided by ``initial_models`` if given); drawn tracks cost nothing."""
        if window.events is None:
            return 0.0, window
        guide = {} if initial_models is None else {"motion": model, "initial_models": initial_models}
        elapsed, tracks = best_of(args.repeats, extract_correspondences, window.events, SENSOR_SIZE, **guide)
        return elapsed, window._replace(src=tracks.src, dst=tracks.dst, dt=tracks.dt)

    _, first = features(windows[0])
    progressive_x(first.src, first.dst, first.dt, model, rng=0)  # warm-up (imports, caches)

    previous: tuple[int, np.ndarray] | None = None
    for index, window in enumerate(windows):
        elapsed, cold_window = features(window)
        cold_features.append(elapsed)
        data = (cold_window.src, cold_window.dst, cold_window.dt, model)
        elapsed, cold = best_of(args.repeats, progressive_x, *data, rng=index)
        cold_ms.append(cold_features[-1] + elapsed)
        row = (len(cold_window.src), window.n_motions, len(cold.params), cold.n_iterations, cold_ms[-1])
        if previous is not None and previous[0] == window.sequence:
            feature_ms, reuse_window = features(window, previous[1])
            reuse_features.append(feature_ms)
            data = (reuse_window.src, reuse_window.dst, reuse_window.dt, model)
            reuse = {"initial_models": previous[1], "rng": index}
            elapsed, reused = best_of(args.repeats, progressive_x, *data, **reuse)
            reuse_ms.append(feature_ms + elapsed)
            row += (len(reuse_window.src), len(reused.params), reused.n_iterations, reuse_ms[-1])
            previous = (window.sequence, reused.params)
        else:
            previous = (window.sequence, cold.params)
        rows.append(row)

    print(
        f"level one, {len(windows)} {args.source} windows, affine4, 1 BLAS thread, "
        f"{cv2.getNumThreads()} OpenCV threads, best of {args.repeats}; times include the features"
    )
    print(" tracks motions | cold: found iters    ms | reuse: tracks found iters    ms")
    for row in rows:
        cold_part = f"{row[0]:7d} {row[1]:7d} | {row[2]:11d} {row[3]:5d} {row[4]:5.1f}"
        reuse_part = f" | {row[5]:13d} {row[6]:5d} {row[7]:5d} {row[8]:5.1f}" if len(row) > 5 else " |"
        print(cold_part + reuse_part)
    known = [row for row in rows if row[1]]
    if known:
        right = [row[2] == row[1] for row in known]
        print(f"motion count right in {100 * np.mean(right):.0f}% of cold windows")
        right = [row[6] == row[1] for row in known if len(row) > 5]
        if right:
            print(f"motion count right in {100 * np.mean(right):.0f}% of reuse windows")
    if any(cold_features):
        print(f"median features cold   {np.median(cold_features):6.1f} ms per window")
    print(f"median level one cold  {np.median(cold_ms):6.1f} ms per window (paper: 110 ms)")
    if reuse_ms:
        if any(reuse_features):
            print(f"median features reuse  {np.median(reuse_features):6.1f} ms per window (guided tracking)")
        count = len(reuse_ms)
        print(
            f"median level one reuse {np.median(reuse_ms):6.1f} ms per window (paper: 15 ms), {count} windows"
        )


if __name__ == "__main__":
    main()
