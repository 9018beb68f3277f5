"""GC-RANSAC: the hypothesis-proposal engine of level one (Barath and Matas, CVPR 2018).

A single-model robust fit of feature correspondences ``src -> dst`` (time gaps ``dt``) to a motion
model of :mod:`evseg_torch.motion`, as in the paper's Sec. IV-A and Algorithm 1:

* **NAPSAC sampling** on the neighbourhood graph: a centre drawn at random, the other ``m - 1`` points
  of the minimal sample drawn from its neighbours; with a compound model, points are drawn with
  weight ``max(1 - pref(C), SAMPLING_FLOOR)``, so that samples land on the data no instance explains yet
  (a small object's 10-30 tracks among 300 would otherwise need thousands of samples);
* **truncated MSAC quality** with the truncated threshold ``1.5 * threshold`` (pitfall 9): a point with
  squared residual ``r2 < (1.5 tau)^2`` contributes its *preference* ``1 - r2 / (1.5 tau)^2``;
* the **compound-model-aware quality** used inside Progressive-X, so that a proposal scores only the
  data that the instances found so far (the compound model ``C``, ``pref_i(C) = max_j pref_i(j)``) do
  not explain. Two forms, chosen by ``quality``:

  - ``"progressive_x"`` (the default): Progressive-X's code, ``Q = S - (sum_i min(pref_i(C),
    pref_i(h))) ** scoring_exponent`` with ``S = sum_i pref_i(h)`` the MSAC score; with exponent 1
    that is ``sum_i max(0, pref_i(h) - pref_i(C))``. It is *not* the paper's Eq. 4;
  - ``"paper"``: the paper's Eq. 4, ``Q = |F| - sum_i min(1, max(e_i(h)^2 / gamma^2, 1 - e_i(C)^2 /
    gamma^2))`` with ``gamma = 1.5 tau`` and ``e_i(C)`` the smallest error under the instances. Since
    ``1 - min(1, max(a, b)) = max(0, min(1 - a, 1 - b))`` and ``e_i(C)^2 / gamma^2 >= 0``, every
    point contributes ``min(pref_i(h), 1 - pref_i(C))``: ``Q = sum_i min(pref_i(h), 1 - pref_i(C))``
    (``scoring_exponent`` plays no part). A point that both ``h`` and ``C`` fit half-way still counts
    half here, where Progressive-X's form counts it 0;

  without a compound model both forms are the MSAC score ``S``;
* the adaptive iteration count ``K = log(1 - conf) / log(1 - eta^m)``, clipped to ``[min_iters,
  max_iters]``, ``eta`` the best model's inlier ratio;
* **local optimisation** whenever a new best model appears: graph-cut inlier/outlier labelling (one
  s-t minimum cut, :func:`graph_cut_inliers`) followed by least-squares refits on all labelled
  inliers and on random subsets of them, repeated while the quality improves;
* a final iteratively re-weighted least-squares polish.

Hypotheses are generated and scored in batches, all residuals of a batch in one matrix product:
every model here is a linear velocity field, ``dst - src = dt J(src) theta``, so the residuals of K
hypotheses are ``b - A @ params.T`` with ``A = dt J(src)`` stacked once per call.

The validated correspondences and NAPSAC's samples live in :mod:`~evseg_torch.level_one.sampling`, the
preference and the graph-cut inlier labelling in :mod:`~evseg_torch.level_one.inliers`; this module
holds the RANSAC loop and re-exports them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.config import LevelOneConfig
from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.level_one.inliers import graph_cut_inliers, preference
from evseg_torch.level_one.sampling import Correspondences
from evseg_torch.motion.base import MotionModel
from evseg_torch.validation import check_integer

__all__ = ["QUALITIES", "gc_ransac", "graph_cut_inliers", "iteration_bound", "preference"]

#: Forms of the compound-model-aware quality: Progressive-X's code (the default) and the paper's Eq. 4.
QUALITIES = ("progressive_x", "paper")

#: Hypotheses generated and scored per vectorised step.
BATCH_SIZE = 128
#: Graph-cut + refit rounds per local optimisation (GC-RANSAC's ``max_graph_cut_number``).
MAX_GRAPH_CUT_NUMBER = 10
#: Random inlier subsets refitted per round (GC-RANSAC's ``max_local_optimization_number``).
MAX_LOCAL_OPTIMIZATION_NUMBER = 10
#: Rounds of the final iteratively re-weighted least squares.
MAX_LEAST_SQUARES_ITERATIONS = 10
#: Sampling weight of a point that the compound model fully explains (unexplained points weigh 1).
SAMPLING_FLOOR = 0.05


def iteration_bound(inlier_ratio: float, sample_size: int, conf: float) -> float:
    """RANSAC's iteration count ``log(1 - conf) / log(1 - eta^m)`` for confidence ``conf``.

    Returns ``inf`` when ``eta^m`` underflows (no inliers) and ``0`` when every point is an inlier.
    """
    hit = float(inlier_ratio) ** sample_size
    if hit >= 1.0:
        return 0.0
    miss = np.log1p(-hit)
    return float(np.log1p(-conf) / miss) if miss < 0 else float("inf")


@dataclass(frozen=True)
class _Scoring:
    """Quality of hypotheses from their preferences: truncated MSAC, aware of the compound model.

    ``quality`` ``"progressive_x"``: the MSAC score minus the support shared with the compound model
    to the power ``exponent``; ``"paper"``: Eq. 4, ``sum_i min(pref_i, 1 - compound_i)``.
    """

    threshold: float
    compound: np.ndarray | None
    exponent: float
    quality: str

    def __call__(self, pref: np.ndarray) -> np.ndarray:
        if self.compound is None:
            return pref.sum(axis=-1)
        if self.quality == "paper":
            return np.minimum(pref, 1.0 - self.compound).sum(axis=-1)
        return pref.sum(axis=-1) - np.minimum(pref, self.compound).sum(axis=-1) ** self.exponent


def _local_optimisation(
    data: Correspondences, params, score, scoring: _Scoring, rng, *, spatial_coherence_weight: float
):
    """GC-RANSAC's local optimisation: graph-cut labelling then refits, while the quality improves."""
    m = data.model.min_samples
    subset = 7 * m
    for _ in range(MAX_GRAPH_CUT_NUMBER):
        inliers = np.flatnonzero(
            graph_cut_inliers(
                data.sq_residuals(params[None])[0],
                data.edges,
                threshold=scoring.threshold,
                spatial_coherence_weight=spatial_coherence_weight,
            )
        )
        if inliers.size < m:
            break
        # One batched solve: all labelled inliers, then random subsets of 7 m of them, as 0/1 weights.
        weights = np.zeros((1 + MAX_LOCAL_OPTIMIZATION_NUMBER * (inliers.size > subset), data.n_points))
        weights[0, inliers] = 1.0
        if inliers.size > subset:
            keys = rng.random((MAX_LOCAL_OPTIMIZATION_NUMBER, inliers.size))
            picks = inliers[np.argpartition(keys, subset - 1, axis=1)[:, :subset]]
            weights[np.arange(1, len(weights))[:, None], picks] = 1.0
        candidates, valid = data.fit_weighted(weights)
        if not valid.any():
            break
        candidates = candidates[valid]
        scores = scoring(preference(data.sq_residuals(candidates), scoring.threshold))
        best = int(np.argmax(scores))
        if scores[best] <= score:
            break
        params, score = candidates[best], scores[best]
    return params, score


def _polish(data: Correspondences, params, score, scoring: _Scoring):
    """Iteratively re-weighted least squares with Tukey-like weights ``pref^2``, kept while improving."""
    for _ in range(MAX_LEAST_SQUARES_ITERATIONS):
        weights = preference(data.sq_residuals(params[None]), scoring.threshold) ** 2
        if np.count_nonzero(weights) < data.model.min_samples:
            break
        candidate, valid = data.fit_weighted(weights)
        if not valid[0]:
            break
        candidate_score = scoring(preference(data.sq_residuals(candidate), scoring.threshold))[0]
        if candidate_score <= score:
            break
        params, score = candidate[0], candidate_score
    return params, score


def run_gc_ransac(
    data: Correspondences,
    *,
    threshold: float,
    conf: float,
    spatial_coherence_weight: float,
    max_iters: int,
    min_iters: int,
    compound_preference: np.ndarray | None,
    scoring_exponent: float,
    rng: np.random.Generator,
    quality: str,
):
    """:func:`gc_ransac` on validated :class:`Correspondences` (Progressive-X calls it repeatedly)."""
    m = data.model.min_samples
    n_points = data.n_points
    if n_points < m:
        return None, np.zeros(n_points, dtype=bool), 0
    scoring = _Scoring(threshold, compound_preference, scoring_exponent, quality)
    # Samples are drawn mostly where the compound model leaves data unexplained: a sample there is the
    # one that can propose an unseen motion (the floor keeps every point drawable).
    weights = None if compound_preference is None else np.maximum(1.0 - compound_preference, SAMPLING_FLOOR)
    truncated = (1.5 * threshold) ** 2
    best, best_score = None, -np.inf
    required = max_iters
    iterations = 0
    while iterations < required:
        count = min(BATCH_SIZE, required - iterations)
        params, valid = data.fit(data.napsac(rng, count, weights))
        iterations += count
        if not valid.any():
            continue
        params = params[valid]
        scores = scoring(preference(data.sq_residuals(params), threshold))
        top = int(np.argmax(scores))
        if scores[top] <= best_score:
            continue
        best, best_score = _local_optimisation(
            data, params[top], scores[top], scoring, rng, spatial_coherence_weight=spatial_coherence_weight
        )
        inlier_ratio = np.count_nonzero(data.sq_residuals(best[None])[0] < truncated) / n_points
        bound = iteration_bound(inlier_ratio, m, conf)
        required = int(np.clip(np.ceil(bound) + 1 if np.isfinite(bound) else max_iters, min_iters, max_iters))
    if best is None:
        return None, np.zeros(n_points, dtype=bool), iterations
    best, _ = _polish(data, best, best_score, scoring)
    inliers = graph_cut_inliers(
        data.sq_residuals(best[None])[0],
        data.edges,
        threshold=threshold,
        spatial_coherence_weight=spatial_coherence_weight,
    )
    return best, inliers, iterations


def check_fitting_parameters(
    *,
    threshold,
    conf,
    spatial_coherence_weight,
    max_iters,
    min_iters=0,
    scoring_exponent,
    quality,
) -> None:
    """Raise :class:`ConfigError` naming the first out-of-range robust-fitting parameter."""
    if not threshold > 0:
        raise ConfigError(f"threshold must be positive, got {threshold}")
    if not 0 < conf < 1:
        raise ConfigError(f"conf must lie in (0, 1), got {conf}")
    if not 0 <= spatial_coherence_weight <= 1:
        raise ConfigError(f"spatial_coherence_weight must lie in [0, 1], got {spatial_coherence_weight}")
    check_integer(max_iters, "max_iters", at_least=1)
    if check_integer(min_iters, "min_iters") > max_iters:
        raise ConfigError(f"min_iters must be at most max_iters, got {min_iters} and {max_iters}")
    if not scoring_exponent > 0:
        raise ConfigError(f"scoring_exponent must be positive, got {scoring_exponent}")
    check_quality(quality)


def check_quality(quality) -> None:
    """Raise :class:`ConfigError` unless ``quality`` is one of :data:`QUALITIES`."""
    if quality not in QUALITIES:
        raise ConfigError(f"quality must be one of {', '.join(map(repr, QUALITIES))}, got {quality!r}")


def gc_ransac(
    src,
    dst,
    dt,
    model: MotionModel,
    *,
    threshold: float = LevelOneConfig.threshold,
    conf: float = LevelOneConfig.conf,
    spatial_coherence_weight: float = LevelOneConfig.spatial_coherence_weight,
    neighborhood_ball_radius: float = LevelOneConfig.neighborhood_ball_radius,
    neighbors=None,
    max_iters: int = LevelOneConfig.max_iters,
    min_iters: int = 20,
    compound_preference=None,
    scoring_exponent: float = LevelOneConfig.scoring_exponent,
    quality: str = LevelOneConfig.quality,
    rng=None,
):
    """Robustly fit one motion model to feature correspondences with GC-RANSAC.

    See the module docstring for the algorithm. Randomness enters only through ``rng``: equal seeds
    give identical results.

    Args:
        src: feature positions at the earlier time, :math:`(N, 2)` pixels.
        dst: the same features ``dt`` later, :math:`(N, 2)`.
        dt: time gaps in seconds, scalar or :math:`(N,)`, non-zero.
        model: a motion model of :mod:`evseg_torch.motion` (its ``min_samples`` is the sample size m).
        threshold: inlier threshold ``tau`` in pixels of transfer error; points count as inliers below
            the truncated threshold ``1.5 tau``. The paper uses 1.5 px for LK tracks.
        conf: RANSAC confidence ``mu`` of the adaptive iteration count (paper: 0.95).
        spatial_coherence_weight: Potts weight ``w`` of the graph-cut labelling, in ``[0, 1]``; 0.14 is
            GC-RANSAC's default, 0 turns the labelling into plain thresholding.
        neighborhood_ball_radius: radius in pixels of the neighbourhood graph on ``dst``.
        neighbors: a ready neighbourhood graph, integer :math:`(E, 2)`; overrides the radius.
        max_iters: cap on the number of minimal samples.
        min_iters: floor on the number of minimal samples (samples come in batches of
            :data:`BATCH_SIZE`, so at least ``min(BATCH_SIZE, max_iters)`` are drawn anyway).
        compound_preference: Progressive-X's compound preference vector :math:`(N,)` in ``[0, 1]``;
            ``None`` for plain single-model fitting.
        scoring_exponent: power of the support shared with the compound model in the
            ``"progressive_x"`` quality (unused by ``"paper"``).
        quality: form of the compound-model-aware quality (module docstring): ``"progressive_x"``,
            Progressive-X's code, or ``"paper"``, the paper's Eq. 4. Without ``compound_preference``
            both are the MSAC score.
        rng: :class:`numpy.random.Generator` or seed.

    Returns:
        ``(params, inliers, n_iterations)``: the model parameters :math:`(P,)` float64, or ``None``
        when no non-degenerate hypothesis was found (too few points, all samples degenerate); the
        graph-cut inlier mask :math:`(N,)` (all False with ``None``); the number of minimal samples
        drawn.

    Raises:
        ModelError: malformed correspondences.
        ConfigError: an out-of-range parameter.
        ShapeError: malformed ``neighbors`` or ``compound_preference``.

    Examples:
        >>> from evseg_torch.motion import Translation
        >>> rng = np.random.default_rng(0)
        >>> src = rng.uniform(0, 100, (50, 2))
        >>> dst = src + np.array([1.0, -2.0])
        >>> dst[:10] = rng.uniform(0, 100, (10, 2))
        >>> params, inliers, _ = gc_ransac(src, dst, 0.01, Translation((100, 100)), rng=0)
        >>> np.round(params, 6).tolist(), int(inliers.sum())
        ([100.0, -200.0], 40)
    """
    settings = {"threshold": threshold, "conf": conf, "spatial_coherence_weight": spatial_coherence_weight}
    check_fitting_parameters(
        **settings,
        max_iters=max_iters,
        min_iters=min_iters,
        scoring_exponent=scoring_exponent,
        quality=quality,
    )
    data = Correspondences.build(
        src, dst, dt, model, neighborhood_ball_radius=neighborhood_ball_radius, neighbors=neighbors
    )
    if compound_preference is not None:
        compound_preference = np.asarray(compound_preference, dtype=np.float64)
        if compound_preference.shape != (data.n_points,):
            raise ShapeError(
                f"compound_preference must have shape ({data.n_points},), got {compound_preference.shape}"
            )
    return run_gc_ransac(
        data,
        **settings,
        max_iters=int(max_iters),
        min_iters=int(min_iters),
        compound_preference=compound_preference,
        scoring_exponent=scoring_exponent,
        rng=np.random.default_rng(rng),
        quality=quality,
    )
