"""Progressive-X: multi-model fitting of feature correspondences (level one; paper Sec. IV-A, Alg. 1).

Progressive-X (Barath and Matas, ICCV 2019) interleaves two steps:

* **proposal**: GC-RANSAC (:mod:`evseg_torch.level_one.gc_ransac`) with a quality that counts only the
  data the instances found so far do not explain (the compound-model-aware score: by default
  Progressive-X's code's form, with ``quality="paper"`` the paper's Eq. 4), so every call
  proposes a not-yet-seen motion; its NAPSAC samples are drawn mostly among those unexplained data,
  which makes the iteration budget below, computed on them, the right one;
* **optimisation**: PEARL (Isack and Boykov, IJCV 2012) relabels all correspondences among the
  instances and an outlier label by α-expansion (:func:`evseg_torch.graphcut.alpha_expansion.alpha_expansion`)
  with a Potts prior on the neighbourhood graph and a label cost per instance, refits the instances
  and drops those left with too few points.

A proposal is accepted if it has at least ``max(m, minimum_point_number)`` inliers, its preference
vector's Tanimoto similarity with the compound preference vector is at most
``maximum_tanimoto_similarity`` and PEARL keeps it. The loop stops when the paper's Eq. 5 bound on
the number of inliers of a still unseen motion, ``U (1 - (1 - conf)^(1/k))^(1/m)`` (``m`` the minimal
sample size), or ``U`` itself falls below that minimum, when ``maximum_model_number`` instances exist,
after 10 consecutive proposals that changed nothing, or after 10 proposals (Progressive-X's hard cap).

``U = sum_i (1 - pref_i(C))`` is the preference that the instances leave unexplained, where
Progressive-X counts the points that PEARL leaves outliers, ``N - N_C``. It bounds the
compound-model-aware quality of any proposal in both forms: ``sum_i max(0, pref_i(h) - pref_i(C))``
(Progressive-X's with ``scoring_exponent`` 1) and ``sum_i min(pref_i(h), 1 - pref_i(C))`` (Eq. 4).
So the loop goes on while a proposal could still score like an instance of the minimum size.
``N - N_C`` does not: PEARL's Potts term pulls nearly every track into an instance, so it falls to 0
as soon as one instance covers two objects whose motions differ by a few pixels, and the proposal that
splits them is never made; with ``U`` close objects more often get instances of their own.

``k`` counts the RANSAC iterations since the instances last changed, not since the start as in
Progressive-X's code: samples drawn before an instance was accepted were scored against another
compound model, and there a motion's own samples lose to the larger motion found first. With the
cumulative count the bound stops the translation model (``m = 1``) right after the background: 128
samples make it ``0.023 U``. For the same reason a proposal's sampling is capped at the count
that makes the bound reach the minimum (a proposal that finds nothing new by then ends the loop).

Historical models (``initial_models``, e.g. the previous window's) bootstrap the instances and the
PEARL labelling before any proposal, so only the correspondences of newly appearing motions still
need sampling; models that lost their support are dropped by PEARL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.config import LevelOneConfig
from evseg_torch.errors import ConfigError
from evseg_torch.graphcut.alpha_expansion import alpha_expansion
from evseg_torch.level_one.gc_ransac import (
    Correspondences,
    check_fitting_parameters,
    iteration_bound,
    preference,
    run_gc_ransac,
)
from evseg_torch.motion.base import MotionModel
from evseg_torch.validation import check_integer

__all__ = ["OUTLIER", "ProgressiveXResult", "pearl", "progressive_x"]

#: Label of correspondences that no motion explains.
OUTLIER = -1
#: Proposals per call (Progressive-X's hard cap on its outer loop).
MAX_PROPOSALS = 10
#: Consecutive proposals that change nothing before giving up (``max_proposal_number_without_change``).
MAX_PROPOSALS_WITHOUT_CHANGE = 10
#: Relabel-and-refit rounds of PEARL.
MAX_PEARL_ITERATIONS = 100
#: α-expansion cycles per PEARL labelling; the expansion stops earlier once a cycle changes nothing.
MAX_EXPANSION_CYCLES = 100


@dataclass(frozen=True)
class ProgressiveXResult:
    """Result of :func:`progressive_x`.

    Attributes:
        params: model instances :math:`(M, P)` float64; row ``m`` is the motion of label ``m``.
        labels: :math:`(N,)` int64 label of every correspondence, :data:`OUTLIER` (``-1``) if none.
        n_proposals: number of GC-RANSAC proposals made.
        n_iterations: cumulative number of RANSAC minimal samples over all proposals.
    """

    params: np.ndarray
    labels: np.ndarray
    n_proposals: int
    n_iterations: int


def _pearl_unary(data: Correspondences, params: np.ndarray, threshold: float, weight: float) -> np.ndarray:
    """PEARL data costs :math:`(N, M)`: ``(1 - w) d`` inside the truncated threshold, else ``2 (1 - w)``."""
    distance = 1.0 - preference(data.sq_residuals(params), threshold).T
    return (1.0 - weight) * np.where(distance < 1.0, distance, 2.0)


def pearl(
    data: Correspondences,
    params: np.ndarray,
    labels: np.ndarray | None,
    *,
    threshold: float,
    spatial_coherence_weight: float,
    label_cost: float,
    min_inliers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """PEARL: alternate α-expansion labelling and least-squares refits until the labelling repeats.

    The energy is the sum of data costs (:func:`_pearl_unary`; the outlier label costs ``1 - w``), a
    Potts term of weight ``w`` on the neighbourhood graph and ``label_cost`` per label in use. An
    instance's refit (least squares on its points, Tukey-weighted by its preferences) is kept only if
    it lowers the data cost of its points, so no refit raises the energy; instances with fewer than
    ``min_inliers`` points are dropped and their points become outliers.

    Args:
        data: validated correspondences with their neighbourhood graph.
        params: instances :math:`(M, P)`.
        labels: initial labels :math:`(N,)` in ``[-1, M)``, or ``None`` for each point's cheapest label.
        threshold, spatial_coherence_weight: as in :func:`progressive_x`.
        label_cost: cost of every label in use, the outlier label included.
        min_inliers: smallest number of points an instance may keep.

    Returns:
        ``(params (M', P), labels (N,))`` with the surviving instances renumbered in their order.
    """
    weight = float(spatial_coherence_weight)
    for _ in range(MAX_PEARL_ITERATIONS):
        if len(params) == 0:
            return params, np.full(data.n_points, OUTLIER, dtype=np.int64)
        unary = _pearl_unary(data, params, threshold, weight)
        new_labels = alpha_expansion(
            unary,
            data.potts,
            smoothness=weight,
            label_cost=label_cost,
            init_labels=labels,
            max_cycles=MAX_EXPANSION_CYCLES,
            outlier_cost=1.0 - weight,
            outlier_label_cost=label_cost,
        ).labels
        changed = labels is None or not np.array_equal(new_labels, labels)
        labels = new_labels
        keep = np.bincount(labels[labels >= 0], minlength=len(params)) >= min_inliers
        if not keep.all():
            # One slot more than instances: label -1 indexes it and stays OUTLIER.
            renumber = np.full(len(params) + 1, OUTLIER, dtype=np.int64)
            renumber[np.flatnonzero(keep)] = np.arange(np.count_nonzero(keep))
            params, labels, changed = params[keep], renumber[labels], True
            unary = unary[:, keep]
            if len(params) == 0:
                continue
        members = labels[None, :] == np.arange(len(params))[:, None]
        # Tukey weights: points that PEARL's smoothness pulled into an instance without fitting it
        # (residual beyond the truncated threshold) must not bias its refit.
        tukey = np.square(np.clip(1.0 - unary.T / (1.0 - weight), 0.0, None)) if weight < 1 else members
        refits, valid = data.fit_weighted(members * tukey)
        own = members.T
        old_cost = np.where(own, unary, 0.0).sum(axis=0)
        new_cost = np.where(own, _pearl_unary(data, refits, threshold, weight), 0.0).sum(axis=0)
        params = np.where((valid & (new_cost < old_cost))[:, None], refits, params)
        # Refits alone keep lowering the energy by ever smaller steps (they iterate re-weighted least
        # squares); the labelling is what PEARL optimises, so a repeated labelling ends the loop.
        if not changed:
            break
    return params, labels


def _tanimoto(a: np.ndarray, b: np.ndarray) -> float:
    """Tanimoto similarity ``a.b / (|a|^2 + |b|^2 - a.b)`` of two preference vectors (0 if both vanish)."""
    dot = float(a @ b)
    denominator = float(a @ a + b @ b) - dot
    return dot / denominator if denominator > 0 else 0.0


def _unseen_inlier_bound(unexplained: float, n_iterations: int, sample_size: int, conf: float) -> float:
    """Paper Eq. 5: with confidence ``conf``, an unseen instance has fewer inliers than this."""
    if n_iterations == 0:
        return float(unexplained)
    miss = -np.expm1(np.log1p(-conf) / n_iterations)
    return float(unexplained * miss ** (1.0 / sample_size))


def progressive_x(
    src,
    dst,
    dt,
    model: MotionModel,
    *,
    threshold: float = LevelOneConfig.threshold,
    conf: float = LevelOneConfig.conf,
    spatial_coherence_weight: float = LevelOneConfig.spatial_coherence_weight,
    neighborhood_ball_radius: float = LevelOneConfig.neighborhood_ball_radius,
    maximum_tanimoto_similarity: float = LevelOneConfig.maximum_tanimoto_similarity,
    max_iters: int = LevelOneConfig.max_iters,
    minimum_point_number: int = LevelOneConfig.minimum_point_number,
    maximum_model_number: int = LevelOneConfig.maximum_model_number,
    scoring_exponent: float = LevelOneConfig.scoring_exponent,
    quality: str = LevelOneConfig.quality,
    initial_models=None,
    rng=None,
) -> ProgressiveXResult:
    """Find every motion among feature correspondences and label each correspondence with one of them.

    Parameter names follow pyprogressivex; the defaults are :class:`~evseg_torch.config.LevelOneConfig`'s,
    chosen for Lucas-Kanade tracks in pixels over 15-35 ms windows (100-300 tracks on a 240x180 or
    346x260 sensor), not copied from pyprogressivex, whose defaults suit homographies (see the method
    reference, pitfall 8).

    Args:
        src: feature positions at the earlier time, :math:`(N, 2)` pixels.
        dst: the same features ``dt`` later, :math:`(N, 2)`.
        dt: time gaps in seconds, scalar or :math:`(N,)`, non-zero.
        model: motion model family of :mod:`evseg_torch.motion`; ``m = model.min_samples``.
        threshold: inlier threshold ``tau`` in pixels of transfer error; decisions use the truncated
            threshold ``1.5 tau``. 1.5 px is the paper's value for LK tracks.
        conf: confidence ``mu`` of GC-RANSAC's iteration count and of the termination bound (paper: 0.95).
        spatial_coherence_weight: Potts weight ``w`` in ``[0, 1]`` of GC-RANSAC's labelling and PEARL.
            0.14 (GC-RANSAC's and Progressive-X's C++ default) rather than pyprogressivex's 0: objects'
            tracks are spatially clustered, which is what the paper's neighbourhood graph exploits.
        neighborhood_ball_radius: radius in pixels of the neighbourhood graph on ``dst``. 15 px gives
            about 6-12 neighbours at the 200-400 tracks of a DAVIS window (pyprogressivex's 200 suits
            megapixel images).
        maximum_tanimoto_similarity: largest Tanimoto similarity between a proposal's preference
            vector and the compound one; 0.5 (the C++ default) rejects re-proposals of found motions
            while accepting a small object next to the background.
        max_iters: cap on GC-RANSAC's minimal samples per proposal (pyprogressivex's 1000).
        minimum_point_number: fewest inliers of an instance; also PEARL's label cost and the level
            of the termination bound. 4 rather than pyprogressivex's 10 or the C++ 20: a small moving
            object often carries only a few tracks, and in the cascade level two's label cost prunes
            the weak models that a low minimum lets through; alone, level one is better served by 10,
            where an instance must save ``10 / (1 - w)`` data cost to pay its label, far more than
            random outlier tracks support.
        maximum_model_number: stop at this many instances; ``-1`` for no limit.
        scoring_exponent: power of the support a proposal shares with the compound model in the
            ``"progressive_x"`` quality; unused by ``"paper"``. 1 rather than Progressive-X's code's
            2: an object's affine motion often agrees with a strip of background tracks, and
            squaring that shared support buries the object's own 10-30 tracks.
        quality: the proposals' compound-model-aware quality (see :mod:`~evseg_torch.level_one.gc_ransac`).
            ``"progressive_x"`` (default): Progressive-X's code, ``sum_i pref_i(h) - (sum_i
            min(pref_i(h), pref_i(C))) ** scoring_exponent``; this is not the paper's Eq. 4.
            ``"paper"``: the paper's Eq. 4, ``sum_i min(pref_i(h), 1 - pref_i(C))``.
        initial_models: historical instances :math:`(M_0, P)` to start from, or ``None``.
        rng: :class:`numpy.random.Generator` or seed; equal seeds give identical results.

    Returns:
        :class:`ProgressiveXResult`. Too few correspondences for one instance give an empty result
        (no instances, every label :data:`OUTLIER`), not an error.

    Raises:
        ModelError: malformed correspondences, or ``initial_models`` of the wrong width.
        ConfigError: an out-of-range parameter.

    Examples:
        >>> from evseg_torch.motion import Translation
        >>> rng = np.random.default_rng(0)
        >>> src = rng.uniform(0, 100, (80, 2))
        >>> dst = src + np.where(src[:, :1] < 50, [1.0, 0.0], [-1.0, 2.0])
        >>> result = progressive_x(src, dst, 0.01, Translation((100, 100)), rng=0)
        >>> np.round(result.params).tolist()
        [[-100.0, 200.0], [100.0, 0.0]]
    """
    settings = {"threshold": threshold, "spatial_coherence_weight": spatial_coherence_weight}
    check_fitting_parameters(
        **settings, conf=conf, max_iters=max_iters, scoring_exponent=scoring_exponent, quality=quality
    )
    if not 0 <= maximum_tanimoto_similarity <= 1:
        raise ConfigError(f"maximum_tanimoto_similarity must be in [0, 1], got {maximum_tanimoto_similarity}")
    check_integer(minimum_point_number, "minimum_point_number")
    data = Correspondences.build(src, dst, dt, model, neighborhood_ball_radius=neighborhood_ball_radius)
    n_points, sample_size = data.n_points, model.min_samples
    min_inliers = max(sample_size, int(minimum_point_number))
    params = np.zeros((0, model.n_params))
    if initial_models is not None:
        params = model.check_instances(initial_models)
    labels = np.full(n_points, OUTLIER, dtype=np.int64)
    if n_points < min_inliers:
        return ProgressiveXResult(np.zeros((0, model.n_params)), labels, 0, 0)

    rng = np.random.default_rng(rng)
    refine = {**settings, "label_cost": float(minimum_point_number), "min_inliers": min_inliers}
    if len(params):
        params, labels = pearl(data, params, None, **refine)
    n_proposals = n_iterations = since_change = without_change = 0
    while n_proposals < MAX_PROPOSALS and without_change < MAX_PROPOSALS_WITHOUT_CHANGE:
        if 0 < maximum_model_number <= len(params):
            break
        compound = preference(data.sq_residuals(params), threshold).max(axis=0) if len(params) else None
        unexplained = float(n_points) if compound is None else float(np.sum(1.0 - compound))
        if unexplained < min_inliers:
            break
        # Sampling beyond the count at which the Eq. 5 bound falls below the minimum cannot change the
        # outcome of a fruitless proposal: Prog-X would stop right after it.
        budget = iteration_bound(min_inliers / unexplained, sample_size, conf)
        budget = int(max_iters) if not np.isfinite(budget) else int(min(max_iters, np.ceil(budget) + 1))
        proposal, inliers, iterations = run_gc_ransac(
            data,
            conf=conf,
            max_iters=budget,
            min_iters=0,
            compound_preference=compound,
            scoring_exponent=scoring_exponent,
            quality=quality,
            rng=rng,
            **settings,
        )
        n_proposals += 1
        n_iterations += iterations
        since_change += iterations
        accepted = proposal is not None and np.count_nonzero(inliers) >= min_inliers
        if accepted and compound is not None:
            proposal_preference = preference(data.sq_residuals(proposal[None])[0], threshold)
            accepted = _tanimoto(proposal_preference, compound) <= maximum_tanimoto_similarity
        if accepted:
            candidate = np.concatenate([params, proposal[None]])
            if len(candidate) == 1:
                candidate_labels = np.where(inliers, 0, OUTLIER)
            else:
                candidate, candidate_labels = pearl(data, candidate, labels, **refine)
            # A proposal that PEARL removes again leaves the instances as they were: no change.
            accepted = len(candidate) > len(params) or not np.array_equal(candidate_labels, labels)
            params, labels = candidate, candidate_labels
        if accepted:
            without_change = since_change = 0
            continue
        without_change += 1
        if _unseen_inlier_bound(unexplained, since_change, sample_size, conf) < min_inliers:
            break
    return ProgressiveXResult(params, labels, n_proposals, n_iterations)
