"""The config's sections: every setting of the pipeline, its default and its documentation.

:class:`SegmenterConfig` holds a window's settings (:class:`WindowConfig`), level one's features
(:class:`FeatureConfig`) and Progressive-X (:class:`LevelOneConfig`), and level two
(:class:`LevelTwoConfig`). Each field is declared with :func:`~evseg_torch.config.fields.setting` (its
default and its bounds) and checked when its section is built; each field's documentation says what it
does and, in a clause, why its default. Import them from :mod:`evseg_torch.config`, which also loads and
writes them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

from evseg_torch.config.fields import Names, Section, setting

__all__ = ["FeatureConfig", "LevelOneConfig", "LevelTwoConfig", "SegmenterConfig", "WindowConfig"]


@dataclass(frozen=True)
class WindowConfig(Section):
    """How a recording is cut into windows.

    Attributes:
        window_ms: window length in milliseconds (the paper uses 15–35 ms).
        stride_ms: step between window starts; ``None`` means ``window_ms`` (no overlap).
        events_per_window: if set, windows hold this many events instead of a fixed duration.
        min_events: windows with fewer events are reported as empty rather than segmented.
    """

    where: ClassVar[str] = "window."

    window_ms: float = setting(30.0, above=0)
    stride_ms: float | None = setting(None, above=0)
    events_per_window: int | None = setting(None, at_least=1)
    min_events: int = setting(200, at_least=0)


@dataclass(frozen=True)
class FeatureConfig(Section):
    """Level one's corners and Lucas-Kanade tracks (:mod:`evseg_torch.level_one.features`).

    Attributes:
        sub_window: length of the early and late event images, as a fraction of the window, in (0, 0.5].
        max_corners: at most this many Shi-Tomasi corners.
        min_distance: minimum distance between corners in pixels.
        quality_level: corners weaker than this fraction of the strongest response are dropped.
        corner_sigma: Gaussian smoothing of the event images before the corner response, pixels.
        lk_win_size: Lucas-Kanade window side in pixels (OpenCV needs at least 3).
        lk_max_level: pyramid levels of Lucas-Kanade.
        fb_threshold: forward-backward round-trip error above which a track is dropped, pixels.
        both_images: detect corners on the late image too and track them backwards, as the paper does.
        guided_tracking: when a previous window's models are reused, start Lucas-Kanade where they
            take each corner, without the pyramid; corners that none of them explains are tracked
            cold (:func:`~evseg_torch.level_one.features.guided_tracks`).
    """

    where: ClassVar[str] = "features."

    sub_window: float = setting(1.0 / 3.0, above=0, at_most=0.5)
    max_corners: int = setting(500, at_least=1)
    min_distance: int = setting(2, at_least=1)
    quality_level: float = setting(0.001, at_least=0, below=1)
    corner_sigma: float = setting(1.0, at_least=0)
    lk_win_size: int = setting(21, at_least=3)
    lk_max_level: int = setting(3, at_least=0)
    fb_threshold: float = setting(0.25, above=0)
    both_images: bool = True
    guided_tracking: bool = True

    def correspondence_settings(self) -> dict:
        """The keywords of :func:`~evseg_torch.level_one.features.extract_correspondences` that this
        section sets (``guided_tracking`` decides whether the pipeline also gives it the models)."""
        return {
            "sub_window": self.sub_window,
            "max_corners": self.max_corners,
            "min_distance": self.min_distance,
            "quality_level": self.quality_level,
            "sigma": self.corner_sigma,
            "win_size": (self.lk_win_size, self.lk_win_size),
            "max_level": self.lk_max_level,
            "fb_threshold": self.fb_threshold,
            "both_images": self.both_images,
        }


@dataclass(frozen=True)
class LevelOneConfig(Section):
    """Progressive-X with GC-RANSAC proposals (:mod:`evseg_torch.level_one.progressive_x`).

    Attributes:
        threshold: inlier-outlier threshold τ in pixels of transfer error; decisions use 1.5 τ
            (paper: 1.5).
        conf: RANSAC confidence μ of the iteration count and of the termination bound, in (0, 1)
            (paper: 0.95).
        spatial_coherence_weight: Potts weight of GC-RANSAC's labelling and of PEARL, in [0, 1]; 0.14 is
            GC-RANSAC's and Progressive-X's C++ default (pyprogressivex: 0), since an object's tracks
            cluster in the image.
        neighborhood_ball_radius: radius of the correspondences' neighbourhood graph, pixels; 15 gives
            the tracks of a DAVIS window about 6-12 neighbours (pyprogressivex's 200 suits megapixel
            images).
        maximum_tanimoto_similarity: proposals more similar than this to the compound model are rejected
            (Progressive-X: 0.5).
        max_iters: maximum RANSAC iterations per proposal (pyprogressivex: 1000).
        minimum_point_number: minimum inliers of an instance; also PEARL's label cost. 4 (pyprogressivex:
            10; beyond the paper): in the cascade, level two's label cost prunes weak models, so level one
            should rather propose a small object's motion from a few tracks than lose it.
        maximum_model_number: at most this many instances; -1 means no limit.
        scoring_exponent: exponent of the support shared with the compound model in the
            ``progressive_x`` quality; 1, where Progressive-X's code has 2, which buries objects whose
            motion a strip of background shares; unused by ``paper``.
        quality: the proposals' compound-model-aware quality (:mod:`evseg_torch.level_one.gc_ransac`).
            ``progressive_x`` (default): Progressive-X's code,
            ``sum_i pref_i(h) - (sum_i min(pref_i(h), pref_i(C)))^scoring_exponent``, which is not the
            paper's Eq. 4; ``paper``: the paper's Eq. 4, ``sum_i min(pref_i(h), 1 - pref_i(C))``, which
            proposes fewer spurious models but also separates fewer objects.
        reuse_models: bootstrap each window with the previous window's models (paper Table III).
        initial_models: what models given to the segmenter (a previous window's, or a network's
            proposals) do. ``augment``: level one runs and starts from them, so its pool holds them and
            what it adds; ``replace``: level one does not run and they are level two's pool (a stream
            then runs level one only on its first window, or after a window that kept no model);
            ``demand`` (default; level one on demand, beyond the paper): as ``augment`` for models given
            to :meth:`~evseg_torch.pipeline.CascadedSegmenter.forward`, while a stream runs level one
            only on every ``refresh_windows``-th window and where no model is carried in, its other
            windows starting from the carried models alone, as with ``replace``.
        refresh_windows: with ``demand``, a stream runs level one on the windows whose index is a
            multiple of this (the index decides, so a resumed stream runs it where the uninterrupted one
            did); 1 runs it on every window, as ``augment``. 4 by default: level one then finds what
            entered the view within four windows, and discovery meanwhile.
        extra_thresholds: inlier thresholds of further Progressive-X runs on the same tracks (same seed,
            no initial models), whose models join the pool level two starts from (beyond the paper). They
            run only in windows that carry no models in: a stream's later windows start from the last
            one's objects, where further pools cost detection. ``[1.25]`` by default, chosen with
            ``level_two.data_sigma``: a slightly tighter run proposes objects that the first one merges
            with a neighbour, for a moderate cost in time.
    """

    where: ClassVar[str] = "level_one."

    threshold: float = setting(1.5, above=0)
    conf: float = setting(0.95, above=0, below=1)
    spatial_coherence_weight: float = setting(0.14, at_least=0, at_most=1)
    neighborhood_ball_radius: float = setting(15.0, above=0)
    maximum_tanimoto_similarity: float = setting(0.5, at_least=0, at_most=1)
    max_iters: int = setting(1000, at_least=1)
    minimum_point_number: int = setting(4, at_least=0)
    maximum_model_number: int = setting(-1, at_least=-1)
    scoring_exponent: float = setting(1.0, above=0)
    quality: str = setting("progressive_x", choices=Names("evseg_torch.level_one.gc_ransac", "QUALITIES"))
    reuse_models: bool = True
    initial_models: str = setting("demand", choices=("augment", "replace", "demand"))
    refresh_windows: int = setting(4, at_least=1)
    extra_thresholds: tuple[float, ...] = setting((1.25,), above=0)

    def progressive_x_settings(self) -> dict:
        """The keywords of :func:`~evseg_torch.level_one.progressive_x.progressive_x` that this section
        sets (all its fields but the pipeline's own ``reuse_models``, ``initial_models`` and
        ``extra_thresholds``)."""
        pipeline_only = {"reuse_models", "initial_models", "refresh_windows", "extra_thresholds"}
        return {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in pipeline_only
        }


@dataclass(frozen=True)
class LevelTwoConfig(Section):
    """EMSGC's spatio-temporal graph cut with contrast-maximisation refits (:mod:`evseg_torch.level_two`).

    These are the settings of :class:`~evseg_torch.level_two.descent.segmenter.GraphCutContrastSegmenter`
    (its keywords, or ``from_config``), defined here only.

    Attributes:
        lambda_data: weight λ_D of the data term (EMSGC: 1).
        lambda_smooth: Potts weight λ_P per unit edge weight (EMSGC: 25–43); 30 by default, within
            EMSGC's values for EED (30–40).
        lambda_label: label cost λ_M per model in use, the MDL term (EMSGC: 8000; 4000 on EED
            occlusions), in windows of up to ``label_cost_events`` events. 6000 by default, chosen with
            ``data_sigma``: a dearer label loses a small object whose level-one model starts a pixel or
            two off in the first labelling, before a refit can sharpen it.
        n_iter_segmentation: outer block-coordinate-descent rounds (EMSGC: 5); 3 by default, which score
            as 5 do in less time.
        n_iter_labeling: α-expansion cycles per labelling (EMSGC: 2); 1 by default, as a second cycle
            changes next to nothing.
        sigma: Gaussian width of the images of warped events in the refits and discovery, pixels
            (EMSGC: 1).
        data_sigma: Gaussian width of the data term's images of warped events, pixels (EMSGC: 1, as its
            refits'; beyond the paper). 0.65 by default, with ``lambda_label`` 6000 and
            ``level_one.extra_thresholds`` [1.25]: a sharper image tells apart motions a pixel or two
            apart over the window (two touching objects, an object and a compromise model that also holds
            its neighbour), and the larger label cost keeps the background's slightly imprecise model from
            splitting for it (``docs/objects.md``).
        objective: contrast objective of the refits, a key of
            :data:`~evseg_torch.level_two.objectives.contrast.CONTRAST_OBJECTIVES` (EMSGC: ``variance``).
        collapse_weight: exponent γ of the refits' event-collapse guard
            (:func:`~evseg_torch.level_two.objectives.contrast.contrast_loss`; beyond the paper); 0
            switches it off (EMSGC's plain objective).
        optimizer: ``lbfgs`` (batched L-BFGS of :mod:`~evseg_torch.level_two.solver.optimizers`) or ``adam``.
        max_iter: optimiser iterations of the first refit, which starts from the initial pool.
        warm_max_iter: iterations of each later refit, which starts from the previous refit's models
            (``None``: ``max_iter``).
        lr: learning rate (Adam) or initial step (L-BFGS) of the refits, in pixels of displacement;
            ``None`` (default) for the optimiser's own default, 1 for L-BFGS and 0.1 for Adam
            (:class:`~evseg_torch.level_two.solver.cmax.ContrastMaximization`).
        temporal_edges: also join consecutive events at the same pixel in the graph (EMSGC: no).
        data_normalization: ``relative`` (each event's image value divided by its best over the pool,
            floored at a quantile of the pool's values) or ``global`` (EMSGC: divided by the global
            maximum). ``relative`` (beyond the paper) separates layers far better on our scenes; see
            :mod:`evseg_torch.level_two.energy.data_term`.
        data_floor_quantile: in ``relative`` normalisation, the quantile, in (0, 1], of the best values
            of the events whose best model is an event's own that floors its best value, so that each
            layer's events are scaled by that layer's own sharpness (``null``: no such floor; beyond the
            paper).
        data_pool_floor_quantile: in ``relative`` normalisation, the quantile, in (0, 1], of all in-image
            values of the pool that floors every event's best value, so that noise and weak texture do
            not get large differences from small values (``null``: none; beyond the paper).
        data_polarity: read each event's data cost from the image of its own polarity's warped events
            (beyond the paper; EMSGC: one image of all events).
        refit_max_events: each refit sees an evenly spaced subsample of at most this many events per
            cluster (``None``: all, as in EMSGC); models fitted on 4000 events are as good and several
            times faster.
        label_tol: stop the outer iterations once at most this fraction of labels changed, in [0, 1)
            (EMSGC: 0).
        site_time_slices: graph-cut sites are the events of one pixel within one of this many time slices
            of the window (``None``: every event is a site, as in EMSGC); 1 cuts the graph 2-4x smaller
            (:func:`~evseg_torch.level_two.energy.graph.site_graph`).
        label_cost_events: the label cost scales with dense windows: a window of N events pays
            ``lambda_label * max(1, N / label_cost_events)`` per label (``None``: ``lambda_label`` whatever
            the window, as in EMSGC). The data cost a spurious model saves grows with the events it
            takes, so dense windows need a dearer label; sparse ones keep ``lambda_label``, which a
            small object's sharper model can pay.
        discovery_rounds: how many times per window level two proposes new models (splits of clusters,
            unions of touching clusters, each fitted by contrast maximisation; the energy decides); 0
            switches discovery off: the paper's level two, which only prunes. A round after the first
            proposes only around the clusters the round before created. See
            :mod:`evseg_torch.level_two.descent.segmenter` and :mod:`evseg_torch.level_two.discovery`.
        carried_discovery_rounds: the pipeline's discovery rounds, at most ``discovery_rounds``, in a window
            that carries models in (a stream's windows after its first, or given ``initial_models``): they
            start from objects that the windows before split and joined already, where a second round
            costs streamed detection (``docs/objects.md``). Level two alone uses ``discovery_rounds``.
        carried_rounds: labellings, at most, of the descent of a stream's window that carries the last
            window's models in, before discovery (models given to a window of one's own, such as a
            network's proposals, take the full descent); ``None``: as a window of its own
            (``n_iter_segmentation``). 2 by default (beyond the paper): a labelling, a refit and a
            labelling settle a window that starts where the last one ended.
        carried_discovery: what discovery proposes in a stream's window that carries models in. ``new``
            (default, beyond the paper): only what the carried models do not explain, the separate
            groups of a cluster (objects that parted, a new object in the background's view) and
            residual regions; no halves or unions of the carried clusters, which the windows before
            judged; and a round whose proposals are all rejected settles the window. ``all``: as a
            window of its own.
        discovery_min_events: fewest events of a region that gets a proposed model.
        discovery_residual_cost: also propose models for connected events whose own model's data cost is
            at least this (of 255); ``None`` (default) for none: with the ``relative`` data term most
            background events of a sparse window cost that much, and every threshold tried lowered
            detection.
        discovery_radius: pixels by which events reach out when grouped into regions.
        discovery_max_proposals: most models proposed at a time (the largest regions).
        discovery_min_gain: a proposal is kept only if it raises its region's contrast by at least this
            fraction over the region's own cluster's model (0: it must not lower it).
        discovery_max_iter: optimiser iterations of each proposal's contrast-maximisation fit.
        objects: a non-background cluster is one object (beyond the paper; see
            :mod:`evseg_torch.level_two.objects`): each label pays ``object_support_cost`` per event
            compensated outside its support, and settled clusters of separate object groups are split;
            ``false`` gives the paper's clusters, one per motion.
        object_support_cost: data-cost units (of 255) an event pays for a non-background label whose
            support its compensated position misses.
        object_radius: pixels by which compensated events reach out when grouped into objects.
        object_support_radius: pixels by which a label's support extends beyond its grouped events.
        object_splits: how many times per window settled clusters are split into their objects.
        object_label_cost: with ``objects``, labels that share a motion
            (:func:`~evseg_torch.motion.shared.shared_motion_groups`) pay the label cost once for the
            motion and this fraction of it for each of its objects (label subset costs, beyond the paper;
            1: every label pays the full cost, as in EMSGC). The background is priced alone.
        soft_temperature: temperature of the per-event soft assignments, a softmax of the negative data
            cost (units of the cost, 0-255; a cost difference of one temperature between two clusters
            is a factor ``e`` between their probabilities; beyond the paper); 20 is calibrated on
            synthetic scenes (``docs/design/level_two.md``).
    """

    where: ClassVar[str] = "level_two."

    lambda_data: float = setting(1.0, at_least=0)
    lambda_smooth: float = setting(30.0, at_least=0)
    lambda_label: float = setting(6000.0, at_least=0)
    n_iter_segmentation: int = setting(3, at_least=1)
    n_iter_labeling: int = setting(1, at_least=1)
    sigma: float = setting(1.0, at_least=0)
    data_sigma: float = setting(0.65, at_least=0)
    objective: str = setting(
        "variance", choices=Names("evseg_torch.level_two.objectives.contrast", "CONTRAST_OBJECTIVES")
    )
    collapse_weight: float = setting(0.375, at_least=0)
    optimizer: str = setting("lbfgs", choices=Names("evseg_torch.level_two.solver.cmax", "OPTIMIZERS"))
    max_iter: int = setting(6, at_least=1)
    warm_max_iter: int | None = setting(3, at_least=1)
    lr: float | None = setting(None, above=0)
    temporal_edges: bool = False
    data_normalization: str = setting(
        "relative", choices=Names("evseg_torch.level_two.energy.data_term", "NORMALIZATIONS")
    )
    data_floor_quantile: float | None = setting(0.9, above=0, at_most=1)
    data_pool_floor_quantile: float | None = setting(0.75, above=0, at_most=1)
    data_polarity: bool = True
    refit_max_events: int | None = setting(4000, at_least=1)
    label_tol: float = setting(0.002, at_least=0, below=1)
    site_time_slices: int | None = setting(1, at_least=1)
    label_cost_events: float | None = setting(15000.0, above=0)
    discovery_rounds: int = setting(2, at_least=0)
    carried_discovery_rounds: int = setting(1, at_least=0)
    carried_rounds: int | None = setting(2, at_least=1)
    carried_discovery: str = setting("new", choices=("all", "new"))
    discovery_min_events: int = setting(100, at_least=1)
    discovery_residual_cost: float | None = setting(None, at_least=0, at_most=255)
    discovery_radius: int = setting(2, at_least=0)
    discovery_max_proposals: int = setting(8, at_least=1)
    discovery_min_gain: float = setting(0.0, at_least=0)
    discovery_max_iter: int = setting(20, at_least=1)
    soft_temperature: float = setting(20.0, above=0)
    objects: bool = True
    object_support_cost: float = setting(64.0, at_least=0)
    object_radius: int = setting(5, at_least=0)
    object_support_radius: int = setting(6, at_least=0)
    object_splits: int = setting(2, at_least=0)
    object_label_cost: float = setting(0.25, at_least=0, at_most=1)


@dataclass(frozen=True)
class SegmenterConfig(Section):
    """Everything :class:`~evseg_torch.pipeline.CascadedSegmenter` needs.

    Attributes:
        motion_model: ``translation``, ``affine4`` (the paper's) or ``rotation3d``.
        focal: ``(fx, fy)`` for ``rotation3d``; ``None`` means ``max(H, W)``.
        seed: seed of every random choice, so runs are reproducible.
    """

    motion_model: str = setting("affine4", choices=Names("evseg_torch.motion", "MOTION_MODELS"))
    focal: tuple[float, float] | None = setting(None, above=0)
    seed: int = setting(0, at_least=0)
    window: WindowConfig = field(default_factory=WindowConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    level_one: LevelOneConfig = field(default_factory=LevelOneConfig)
    level_two: LevelTwoConfig = field(default_factory=LevelTwoConfig)
