"""Hyper-parameters as nested frozen dataclasses, loaded strictly from YAML.

Every hyper-parameter of the pipeline is documented once, here. Names follow EMSGC (``lambda_smooth``,
``lambda_label``, ``n_iter_segmentation``) and pyprogressivex (``threshold``, ``conf``,
``minimum_point_number``). Field names are unique across sections, so a flat keyword such as
``lambda_smooth=40`` names exactly one field (:func:`replace_config`). Unknown keys, in files or in
keywords, are errors that name the key.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from evseg_torch.errors import ConfigError


@dataclass(frozen=True)
class WindowConfig:
    """How a recording is cut into windows.

    Attributes:
        window_ms: window length in milliseconds (the paper uses 15–35 ms).
        stride_ms: step between window starts; ``None`` means ``window_ms`` (no overlap).
        events_per_window: if set, windows hold this many events instead of a fixed duration.
        min_events: windows with fewer events are reported as empty rather than segmented.
    """

    window_ms: float = 30.0
    stride_ms: float | None = None
    events_per_window: int | None = None
    min_events: int = 200


@dataclass(frozen=True)
class FeatureConfig:
    """Level one's corners and Lucas-Kanade tracks (:mod:`evseg_torch.level_one.features`).

    Attributes:
        sub_window: length of the early and late event images, as a fraction of the window.
        max_corners: at most this many Shi-Tomasi corners.
        min_distance: minimum distance between corners in pixels.
        quality_level: corners weaker than this fraction of the strongest response are dropped.
        corner_sigma: Gaussian smoothing of the event images before the corner response, pixels.
        lk_win_size: Lucas-Kanade window side in pixels.
        lk_max_level: pyramid levels of Lucas-Kanade.
        fb_threshold: forward-backward round-trip error above which a track is dropped, pixels.
        both_images: detect corners on the late image too and track them backwards, as the paper does.
        guided_tracking: when a previous window's models are reused, start Lucas-Kanade where they
            take each corner, without the pyramid; corners that none of them explains are tracked
            cold (:func:`~evseg_torch.level_one.features.guided_tracks`).
    """

    sub_window: float = 1.0 / 3.0
    max_corners: int = 500
    min_distance: int = 2
    quality_level: float = 0.001
    corner_sigma: float = 1.0
    lk_win_size: int = 21
    lk_max_level: int = 3
    fb_threshold: float = 0.25
    both_images: bool = True
    guided_tracking: bool = True


@dataclass(frozen=True)
class LevelOneConfig:
    """Progressive-X with GC-RANSAC proposals (:mod:`evseg_torch.level_one.progressive_x`).

    Attributes:
        threshold: inlier-outlier threshold τ in pixels (paper: 1.5); decisions use 1.5 τ.
        conf: RANSAC confidence μ (paper: 0.95).
        spatial_coherence_weight: Potts weight of GC-RANSAC's labelling and of PEARL.
        neighborhood_ball_radius: radius of the correspondences' neighbourhood graph, pixels.
        maximum_tanimoto_similarity: proposals more similar than this to the compound model are rejected.
        max_iters: maximum RANSAC iterations per proposal.
        minimum_point_number: minimum inliers of an instance; also PEARL's label cost. 4 by default
            (level one alone is tested with 10): in the cascade, level two's label cost prunes weak
            models, so level one should rather propose a small object's motion from a few tracks
            than lose it. On synthetic seeds 0-39 (3 pipeline seeds each) 10 → 4 raises detection
            from 0.88 to 0.93 and mean object IoU from 0.76 to 0.80, cluster-count error -0.32 → -0.08.
        maximum_model_number: at most this many instances; -1 means no limit.
        scoring_exponent: exponent of the support shared with the compound model in the
            ``progressive_x`` proposal quality (pyprogressivex: 2, which buries objects whose motion a
            strip of background shares); unused by ``paper``.
        quality: the proposals' compound-model-aware quality. ``progressive_x`` (default):
            Progressive-X's code, ``sum_i pref_i(h) - (sum_i min(pref_i(h), pref_i(C)))^scoring_exponent``,
            which is not the paper's Eq. 4; ``paper``: the paper's Eq. 4, i.e.
            ``sum_i min(pref_i(h), 1 - pref_i(C))`` (:mod:`evseg_torch.level_one.gc_ransac`). Eq. 4
            proposes fewer spurious models but separates fewer objects: full pipeline, 3 seeds,
            ``shared/data/synthetic_probe`` IoU 0.704 → 0.689, detection 0.74 → 0.72; synthetic seeds
            0-19 IoU 0.834 → 0.801, detection 0.96 → 0.92.
        reuse_models: bootstrap each window with the previous window's models (paper Table III).
        initial_models: what models given to the segmenter (a previous window's, or a network's
            proposals) do. ``augment`` (default): level one runs and starts from them, so its pool holds
            them and what it adds; ``replace``: level one does not run and they are level two's pool (a
            stream then runs level one only on its first window, or after a window that kept no model).
    """

    threshold: float = 1.5
    conf: float = 0.95
    spatial_coherence_weight: float = 0.14
    neighborhood_ball_radius: float = 15.0
    maximum_tanimoto_similarity: float = 0.5
    max_iters: int = 1000
    minimum_point_number: int = 4
    maximum_model_number: int = -1
    scoring_exponent: float = 1.0
    quality: str = "progressive_x"
    reuse_models: bool = True
    initial_models: str = "augment"

    def __post_init__(self):
        if self.quality not in ("progressive_x", "paper"):
            raise ConfigError(f"level_one.quality must be 'progressive_x' or 'paper', got {self.quality!r}")
        if self.initial_models not in ("augment", "replace"):
            raise ConfigError(
                f"level_one.initial_models must be 'augment' or 'replace', got {self.initial_models!r}"
            )


@dataclass(frozen=True)
class LevelTwoConfig:
    """EMSGC's spatio-temporal graph cut with contrast-maximisation refits (:mod:`evseg_torch.level_two`).

    Attributes:
        lambda_data: weight λ_D of the data term (EMSGC: 1).
        lambda_smooth: Potts weight λ_P (EMSGC: 25–43).
        lambda_label: label cost λ_M, the MDL term (EMSGC: 8000; 4000 on EED occlusions), in windows of up
            to ``label_cost_events`` events. 4000 by default:
            with 8000 an object of ~1000 events (5% of a synthetic window) whose level-one model starts
            ~1.5 px off loses its cluster in the first labelling, before a refit can sharpen it.
        n_iter_segmentation: outer block-coordinate-descent iterations (EMSGC: 5). 3 by default: over
            pipeline seeds 0-2 the probe, `hard` and own scenes and EED score within 0.002 of 5 rounds
            (EED's detection rates equal), and level two takes 0.85 of the time (median per window).
        n_iter_labeling: α-expansion cycles per labelling (EMSGC: 2; one loses nothing measurable here).
        sigma: Gaussian width of the images of warped events, pixels (EMSGC: 1).
        optimizer: ``lbfgs`` or ``adam`` for the contrast-maximisation refits.
        max_iter: optimiser iterations of the first refit.
        warm_max_iter: iterations of the later, warm-started refits (``None``: ``max_iter``).
        lr: learning rate (Adam) or initial step (L-BFGS).
        data_normalization: ``relative`` (each event's image value divided by its best over the pool,
            floored at the pool's 90th percentile) or ``global`` (EMSGC: divided by the global maximum).
            Relative separates layers far better on our scenes; see :mod:`evseg_torch.level_two.data_term`.
        data_polarity: read each event's data cost from the image of its own polarity's warped events
            (EMSGC: one image of all events).
        refit_max_events: each refit sees an evenly spaced subsample of at most this many events per
            cluster (``None``: all); models fitted on 4000 events are as good and several times faster.
        label_tol: stop the outer iterations once at most this fraction of labels changed (EMSGC: 0).
        site_time_slices: graph-cut sites are the events of one pixel within one of this many time slices
            of the window (``None``: every event is a site, as in EMSGC); 1 cuts the graph 2-4x smaller.
        label_cost_events: the label cost scales with dense windows: a window of N events pays
            ``lambda_label * max(1, N / label_cost_events)`` per label (``None``: ``lambda_label`` whatever
            the window, as in EMSGC). The data cost a spurious model saves grows with the events it
            takes, so dense windows need a dearer label; sparse ones keep ``lambda_label``, which a
            small object's sharper model can pay.
        discovery_rounds: how many times per window level two proposes new models (splits of clusters,
            unions of touching clusters, each fitted by contrast maximisation; the energy decides); 0
            switches discovery off: the paper's level two, which only prunes. See
            :mod:`evseg_torch.level_two.segmenter` and :mod:`evseg_torch.level_two.discovery`.
        discovery_min_events: fewest events of a region that gets a proposed model.
        discovery_residual_cost: also propose models for connected events whose own model's data cost is
            at least this (of 255); ``None`` for none (every threshold tried lowered detection on the
            probe scenes, see :class:`~evseg_torch.level_two.segmenter.GraphCutContrastSegmenter`).
        discovery_radius: pixels by which events reach out when grouped into regions.
        discovery_max_proposals: most models proposed at a time (the largest regions).
        discovery_min_gain: a proposal is kept only if it raises its region's contrast by at least this
            fraction over the region's own cluster's model (0: it must not lower it).
        discovery_max_iter: optimiser iterations of each proposal's contrast-maximisation fit.
        soft_temperature: temperature of the per-event soft assignments, a softmax of the negative data
            cost (units of the cost, 0-255); 20 is calibrated on synthetic scenes (see
            :data:`~evseg_torch.level_two.segmenter.DEFAULT_SOFT_TEMPERATURE`).
    """

    lambda_data: float = 1.0
    lambda_smooth: float = 30.0
    lambda_label: float = 4000.0
    n_iter_segmentation: int = 3
    n_iter_labeling: int = 1
    sigma: float = 1.0
    optimizer: str = "lbfgs"
    max_iter: int = 6
    warm_max_iter: int | None = 3
    lr: float = 1.0
    data_normalization: str = "relative"
    data_polarity: bool = True
    refit_max_events: int | None = 4000
    label_tol: float = 0.002
    site_time_slices: int | None = 1
    label_cost_events: float | None = 15000.0
    discovery_rounds: int = 1
    discovery_min_events: int = 100
    discovery_residual_cost: float | None = None
    discovery_radius: int = 2
    discovery_max_proposals: int = 8
    discovery_min_gain: float = 0.0
    discovery_max_iter: int = 20
    soft_temperature: float = 20.0


@dataclass(frozen=True)
class SegmenterConfig:
    """Everything :class:`~evseg_torch.pipeline.CascadedSegmenter` needs.

    Attributes:
        motion_model: ``translation``, ``affine4`` (the paper's) or ``rotation3d``.
        focal: ``(fx, fy)`` for ``rotation3d``; ``None`` means ``max(H, W)``.
        seed: seed of every random choice, so runs are reproducible.
    """

    motion_model: str = "affine4"
    focal: tuple[float, float] | None = None
    seed: int = 0
    window: WindowConfig = field(default_factory=WindowConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    level_one: LevelOneConfig = field(default_factory=LevelOneConfig)
    level_two: LevelTwoConfig = field(default_factory=LevelTwoConfig)


def config_from_dict(data: dict, cls: type = SegmenterConfig, where: str = ""):
    """Build a config dataclass from a (nested) mapping, rejecting unknown keys and wrong types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where or 'config'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown config key {where}{unknown[0]!r}; known keys here: {sorted(names)}")
    values = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            values[name] = config_from_dict(value, hint, f"{where}{name}.")
        else:
            values[name] = _coerce(value, hint, f"{where}{name}")
    return cls(**values)


def config_to_dict(config) -> dict:
    """A plain nested dict of a config (tuples become lists), ready for YAML or JSON."""
    return _plain(dataclasses.asdict(config))


def load_config(path: str | Path) -> SegmenterConfig:
    """Load a YAML config file strictly; keys left out keep their defaults."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read config file {path}: {err.strerror or err}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {path} is not valid YAML: {err}") from None
    try:
        return config_from_dict(data or {})
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def dump_config(config: SegmenterConfig, path: str | Path) -> None:
    """Write a config as YAML (it loads back equal with :func:`load_config`)."""
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))


def replace_config(config: SegmenterConfig, **overrides) -> SegmenterConfig:
    """A copy of ``config`` with fields replaced by their flat names, e.g. ``lambda_smooth=40``.

    A whole section may be replaced too (``level_two=LevelTwoConfig(...)`` or a dict of its fields).
    """
    sections = {
        f.name: f.type
        for f in dataclasses.fields(config)
        if dataclasses.is_dataclass(getattr(config, f.name))
    }
    top, nested = {}, {name: {} for name in sections}
    for key, value in overrides.items():
        if key in sections:
            top[key] = (
                value
                if dataclasses.is_dataclass(value)
                else config_from_dict(value, type(getattr(config, key)), f"{key}.")
            )
            continue
        owner = next(
            (s for s in sections if key in {f.name for f in dataclasses.fields(getattr(config, s))}), None
        )
        if owner is None and key not in {f.name for f in dataclasses.fields(config)}:
            raise ConfigError(f"unknown config key {key!r}")
        if owner is None:
            top[key] = _coerce(value, typing.get_type_hints(SegmenterConfig)[key], key)
        else:
            nested[owner][key] = value
    for section, values in nested.items():
        if values:
            current = config_to_dict(top.get(section, getattr(config, section)))
            top[section] = config_from_dict(
                {**current, **values}, type(getattr(config, section)), f"{section}."
            )
    return dataclasses.replace(config, **top)


def _coerce(value, hint, where: str):
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    if value is None:
        if type(None) in options:
            return None
        raise ConfigError(f"config key {where!r} must not be null")
    errors = []
    for option in options:
        if option is type(None):
            continue
        try:
            return _coerce_one(value, option)
        except (TypeError, ValueError) as err:
            errors.append(str(err))
    raise ConfigError(f"config key {where!r} has invalid value {value!r}: {'; '.join(errors)}")


def _coerce_one(value, hint):
    if typing.get_origin(hint) is tuple:
        kinds = typing.get_args(hint)
        if not isinstance(value, list | tuple) or len(value) != len(kinds):
            raise TypeError(f"expected a list of {len(kinds)} values")
        return tuple(_coerce_one(v, k) for v, k in zip(value, kinds, strict=True))
    if hint is bool:
        if not isinstance(value, bool):
            raise TypeError("expected true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError("expected an integer")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError("expected a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise TypeError("expected a string")
        return value
    raise TypeError(f"unsupported type {hint}")


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value
