"""The cascaded segmenter: level one's model pool feeds level two's event clustering.

This is the only module that knows both levels (level one never imports level two and vice versa).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from numbers import Real
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import SegmenterConfig, load_config, replace_config
from evseg_torch.errors import ConfigError, EventFormatError, ModelError
from evseg_torch.events import EventBatch, as_events, check_sensor_size, iter_windows, to_torch
from evseg_torch.level_one.features import Correspondences, extract_correspondences
from evseg_torch.level_one.progressive_x import ProgressiveXResult, progressive_x
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import MotionModel, make_motion_model
from evseg_torch.tracking import (
    ObjectTracker,
    TrackedClusters,
    describe_clusters,
    shared_motion_groups,
    window_duration,
)
from evseg_torch.validation import check_integer

_MAX_SPAN_US = np.iinfo(np.int64).max
# Corner responses and Lucas-Kanade pyramids need a few pixels each way; smaller sensors skip level one.
_MIN_FEATURE_SIZE = 16
# Level two holds several float images of the sensor per model; beyond this it would exhaust memory.
_MAX_PIXELS = 1 << 24


@dataclass(frozen=True)
class Segmentation:
    """The result of segmenting one window.

    ``labels``, ``models``, ``warped_xy``, ``iwes`` and ``soft_assignments`` are NumPy arrays, or torch
    tensors on the segmenter's device when it was given a tensor or an
    :class:`~evseg_torch.events.EventBatch` (the dtypes below are then the module's); everything else
    is NumPy either way.

    Attributes:
        labels: cluster of each event in input order, int64 :math:`(N,)`; ``-1`` only for events
            assigned to no model (never, unless the window could not be segmented).
        models: row ``k`` is the model of label ``k``, float64 :math:`(K, P)`, in the
            :mod:`evseg_torch.motion` convention (rates per second, centred coordinates).
        motion_model: the name of the models' family.
        warped_xy: every event warped by its own cluster's model to ``t_ref``, float64 :math:`(N, 2)`.
        t_ref: reference time, seconds in the input's time base.
        feature_tracks: level one's correspondences.
        feature_labels: level one's cluster of each correspondence, ``-1`` for outliers, :math:`(M,)`.
        level_one_models: level one's model pool, :math:`(M_1, P)`, before level two.
        iwes: each cluster's compensated image of its own events, :math:`(K, H, W)`.
        soft_assignments: each event's probability of each cluster, :math:`(N, K)`: a softmax of level
            two's negative data cost at ``level_two.soft_temperature`` (for distillation; the labels
            come from the graph cut, which also weighs the neighbours, and differ on about a fifth of
            the events).
        energy_history: level two's energy after each labelling.
        timings_ms: milliseconds spent in ``features``, ``level_one``, ``level_two`` and ``total``.
        sensor_size: ``(H, W)``.
        events: the window's canonical events.
        offset: index of the window's first event in the stream (0 for a single window).
        window_index: the window's number in the stream (0 for a single window).
        centres: the median ``[x, y]`` of each cluster's events warped to ``t_ref``, px, float64
            :math:`(K, 2)`; NaN rows for clusters without events.
        boxes: each cluster's events warped to ``t_ref``, as boxes ``[x, y, w, h]`` from the 2nd to the
            98th percentile of x and y, px, float64 :math:`(K, 4)`; NaN rows for clusters without events.
        object_ids: the object id of each cluster, int64 :math:`(K,)` (:mod:`evseg_torch.tracking`): 0
            for the background (the cluster of most events, when its box covers at least half the
            sensor), then 1, 2, ... By :meth:`CascadedSegmenter.stream`, an object keeps its id from
            window to window and ids are never reused; a single window (:meth:`CascadedSegmenter.forward`,
            :meth:`~CascadedSegmenter.segment_batch`) is numbered as a stream's first: the background 0,
            the other clusters from 1 in cluster order.
        shared_motion: which clusters share a motion, int64 :math:`(K,)`: the lowest index of the
            clusters whose models move the points of their boxes less than 2 px apart over the window
            (its own index when none does; :func:`~evseg_torch.motion.shared.shared_motion_groups`).
    """

    labels: np.ndarray
    models: np.ndarray
    motion_model: str
    warped_xy: np.ndarray
    t_ref: float
    feature_tracks: Correspondences
    feature_labels: np.ndarray
    level_one_models: np.ndarray
    iwes: np.ndarray
    soft_assignments: np.ndarray
    energy_history: tuple[float, ...]
    timings_ms: dict[str, float]
    sensor_size: tuple[int, int]
    events: np.ndarray
    offset: int = 0
    window_index: int = 0
    centres: np.ndarray | None = None
    boxes: np.ndarray | None = None
    object_ids: np.ndarray | None = None
    shared_motion: np.ndarray | None = None

    @property
    def n_clusters(self) -> int:
        return int(self.models.shape[0])


class CascadedSegmenter(nn.Module):
    """Event motion segmentation by cascaded two-level multi-model fitting (Lu, Zhou, Shen, IROS 2021).

    Level one (NumPy) detects Shi-Tomasi corners on raw event images, tracks them with Lucas-Kanade and
    clusters the tracks with Progressive-X; its models seed level two (torch), which labels every event
    by graph cuts and refits each cluster's model by contrast maximisation. Being an ``nn.Module``, it
    moves with ``.to(device)``; level one always runs on the CPU.

    Args:
        sensor_size: ``(H, W)``.
        config: a :class:`~evseg_torch.config.SegmenterConfig`; defaults equal the bundled ``default.yaml``.
        **overrides: flat overrides of any config field, e.g. ``lambda_smooth=40``.

    Examples:
        >>> from evseg_torch.synthetic import make_scene
        >>> scene = make_scene((90, 120), n_objects=1, rng=0)
        >>> result = CascadedSegmenter(sensor_size=(90, 120))(scene.events)
        >>> result.labels.shape == scene.labels.shape
        True
    """

    def __init__(
        self, sensor_size: tuple[int, int], config: SegmenterConfig | None = None, **overrides
    ) -> None:
        super().__init__()
        self.sensor_size = check_sensor_size(sensor_size)
        if self.sensor_size[0] * self.sensor_size[1] > _MAX_PIXELS:
            raise ConfigError(
                f"sensor_size {self.sensor_size} has more than {_MAX_PIXELS} pixels; "
                "crop or bin the events first"
            )
        self.config = replace_config(config or SegmenterConfig(), **overrides)
        cfg = self.config
        self.motion: MotionModel = make_motion_model(
            cfg.motion_model,
            self.sensor_size,
            **({"focal": cfg.focal} if cfg.motion_model == "rotation3d" else {}),
        )
        self.level_two = GraphCutContrastSegmenter.from_config(cfg.level_two, self.motion, self.sensor_size)
        # Follows .to(device) and .double(), so level two runs where the caller put the module.
        self.register_buffer("_anchor", torch.zeros(0), persistent=False)

    @classmethod
    def from_config(cls, path: str | Path, sensor_size: tuple[int, int], **overrides) -> CascadedSegmenter:
        """Build from a YAML file (a bundled one: :func:`~evseg_torch.config.bundled_config`), with optional
        flat overrides."""
        return cls(sensor_size, load_config(path), **overrides)

    def extra_repr(self) -> str:
        return f"sensor_size={self.sensor_size}, motion_model={self.config.motion_model!r}"

    def forward(
        self, events, t_ref: float | None = None, initial_models: np.ndarray | Tensor | None = None
    ) -> Segmentation | list[Segmentation]:
        """Segment one window, or each window of a padded batch.

        Args:
            events: the window's events in any form :func:`~evseg_torch.events.as_events` accepts, a torch
                tensor :math:`(N, 4)` ``[t_seconds, x, y, p]`` or an :class:`~evseg_torch.events.EventBatch`
                (on any device; a padded batch of B windows gives B results).
            t_ref: reference time in seconds of the input's time base; defaults to the first event.
            initial_models: models to start from, :math:`(M, P)` (a previous window's, or a network's
                proposals; :math:`(B, M, P)` for a padded batch); NumPy or torch. The config's
                ``level_one.initial_models`` says whether level one augments them or is skipped.

        Returns:
            :class:`Segmentation` (a list of them for a padded batch). When ``events`` is a tensor or an
            ``EventBatch``, its ``labels``, ``models``, ``warped_xy``, ``iwes`` and ``soft_assignments``
            are torch tensors on the module's device; level one's outputs and ``events`` stay NumPy.

        Raises:
            EventFormatError: the events are invalid (see :func:`~evseg_torch.events.as_events`), all at
                one time, or ``t_ref`` is not a finite number of seconds within int64 microseconds of them.
            ModelError: ``initial_models`` is malformed.
        """
        if isinstance(events, EventBatch) and events.is_batched:
            return self.segment_batch(events.unbatch(), t_ref, initial_models)
        return self.segment_batch([events], t_ref, None if initial_models is None else [initial_models])[0]

    def segment_batch(
        self,
        windows: Sequence,
        t_ref: float | None = None,
        initial_models: Sequence | None = None,
        level_one: Sequence[bool] | None = None,
    ) -> list[Segmentation]:
        """Segment several windows, with one batched level two for all of them.

        Level one runs window by window (NumPy, CPU); level two labels and refits every window in one
        batched call (:class:`~evseg_torch.level_two.descent.segmenter.GraphCutContrastSegmenter`). Each
        window's result equals what :meth:`forward` gives for it alone.

        Args:
            windows: B windows, each in any form :meth:`forward` accepts for one window.
            t_ref: reference time of every window, seconds; defaults to each window's first event.
            initial_models: one :math:`(M, P)` stack (or ``None``) per window.
            level_one: for a stream's windows (:meth:`stream` gives it): whether level one runs in each
                window that carries models in (a window without runs it always), and such a window
                takes level two's carried descent (``level_two.carried_rounds``, ``carried_discovery``).
                ``None`` (windows of one's own, given models or not): level one runs unless
                ``level_one.initial_models`` is ``replace``, and level two takes the full descent.

        Returns:
            One :class:`Segmentation` per window, in order; ``timings_ms["level_two"]`` is the batched
            call's time divided by B.

        Raises:
            EventFormatError: a window is invalid (see :meth:`forward`).
            ModelError: ``initial_models`` does not hold one entry per window, or one is malformed.
        """
        windows = list(windows)
        if initial_models is None:
            initial_models = [None] * len(windows)
        if len(initial_models) != len(windows):
            raise ModelError(
                f"initial_models must hold one (M, P) stack per window ({len(windows)}), "
                f"got {len(initial_models)}"
            )
        as_tensors = [isinstance(window, (Tensor, EventBatch)) for window in windows]
        starts = [time.perf_counter()]
        prepared = []
        streamed = level_one is not None
        if level_one is None:
            level_one = [self._runs_level_one()] * len(windows)
        for window, models, runs in zip(windows, initial_models, level_one, strict=True):
            events = as_events(_event_rows(window), self.sensor_size)
            if isinstance(models, Tensor):
                models = models.detach().cpu().numpy()
            t_ref_us = _reference_us(events, t_ref)
            prepared.append((events, t_ref_us, *self._level_one(events, t_ref_us, models, runs)))
            starts.append(time.perf_counter())
        device, dtype = self._device_dtype()
        batches = [
            to_torch(events, t_ref_us=t_ref_us, device=device, dtype=dtype)
            for events, t_ref_us, *_ in prepared
        ]
        pools = [
            torch.as_tensor(
                fitted.params if len(fitted.params) else np.zeros((1, self.motion.n_params)),
                device=device,
                dtype=dtype,
            )
            for *_, fitted, _ in prepared
        ]
        # A window that carries models in starts from objects the windows before split and joined already.
        settings = self.config.level_two
        rounds = [
            min(settings.discovery_rounds, settings.carried_discovery_rounds)
            if _carries(models)
            else settings.discovery_rounds
            for models in initial_models
        ]
        with torch.no_grad():
            carried = [streamed and _carries(models) for models in initial_models]
            twos = self.level_two(batches, pools, discovery_rounds=rounds, carried=carried)
        level_two_ms = 1e3 * (time.perf_counter() - starts[-1]) / len(windows)
        return [
            self._result(item, batch, two, level_one_ms, level_two_ms, tensors)
            for item, batch, two, level_one_ms, tensors in zip(
                prepared, batches, twos, np.diff(starts) * 1e3, as_tensors, strict=True
            )
        ]

    def stream(
        self,
        events,
        window_ms: float | None = None,
        stride_ms: float | None = None,
        events_per_window: int | None = None,
        batch_size: int = 1,
        segment_windows: Callable[[list, np.ndarray | None, list[bool]], list[Segmentation]] | None = None,
        first_window: int = 0,
        max_windows: int | None = None,
        initial_models: np.ndarray | None = None,
        initial_objects: TrackedClusters | None = None,
        next_object_id: int = 1,
    ) -> Iterator[Segmentation]:
        """Segment sliding windows, each starting from the last one's models (carried forward).

        A window that carries models in takes a shorter descent (``level_two.carried_rounds``,
        ``carried_discovery``) and, with ``level_one.initial_models: demand``, runs level one only every
        ``refresh_windows`` windows: it pays for what changed since the window before.

        Args:
            events: all events (any accepted form), or an iterable of canonical chunks of a recording.
            window_ms, stride_ms, events_per_window: window geometry; default from the config.
            batch_size: windows segmented together by :meth:`segment_batch`. With more than one, every
                window of a batch starts from the models of the last window of the batch before (the
                windows of a batch are segmented at once, so none can wait for its predecessor's).
            segment_windows: segments one batch: called with the batch's windows (a list of canonical
                event arrays), the models all of them start from (:math:`(M, P)`, or ``None``) and
                whether level one runs in each (``level_one.initial_models``), it returns one
                :class:`Segmentation` per window, in order. Default: this segmenter, in this
                process (:meth:`segment_batch`). ``evseg_torch.app.workers.WindowPool(segmenter, n).segment``
                shares a batch's windows out among ``n`` processes, one torch thread each, with the results
                of one process on one torch thread, window by window.
            first_window: windows before this index are cut but not segmented: a stopped stream resumes
                here, with ``initial_models`` the models of the last window it segmented (its batches then
                line up with the uninterrupted stream's when it stopped after a whole batch).
            max_windows: cut only the windows of index below this (``None``: all); reading stops there.
            initial_models: models the first batch starts from, :math:`(M, P)`, as reuse would give them.
            initial_objects: the clusters of the window before ``first_window``, whose objects the first
                window continues (a stopped stream's last window; :mod:`evseg_torch.tracking`).
            next_object_id: the least object id not given yet (1 plus the largest a stopped stream gave).

        Yields:
            :class:`Segmentation` of each window with at least ``min_events`` events; its ``offset`` and
            ``window_index`` place it in the stream, and its ``object_ids`` follow objects from window to
            window (assigned here, window after window, so neither batches nor ``segment_windows``
            change them).

        Raises:
            ConfigError: ``batch_size``, ``first_window``, ``max_windows`` or ``next_object_id`` is not an
                integer in its range.
        """
        check_integer(batch_size, "batch_size", at_least=1)
        check_integer(first_window, "first_window")
        check_integer(1 if max_windows is None else max_windows, "max_windows", at_least=1)
        check_integer(next_object_id, "next_object_id", at_least=1)
        segment = self._segment if segment_windows is None else segment_windows
        chunks = _as_chunks(events, self.sensor_size)
        windows = self.config.window
        if window_ms is None and events_per_window is None:
            window_ms, events_per_window = windows.window_ms, windows.events_per_window
            if events_per_window is not None:
                window_ms = None
        stride_ms = stride_ms if stride_ms is not None else (windows.stride_ms if window_ms else None)
        cut = iter_windows(
            chunks, window_ms=window_ms, stride_ms=stride_ms, events_per_window=events_per_window
        )
        if max_windows is not None:
            cut = itertools.takewhile(lambda window: window.index < max_windows, cut)
        kept = (
            window
            for window in cut
            if window.index >= first_window and len(window.events) >= windows.min_events
        )
        previous = None
        if initial_models is not None and self.config.level_one.reuse_models:
            models = np.asarray(_numpy(initial_models), dtype=np.float64)
            if models.ndim != 2 or models.shape[1] != self.motion.n_params:
                raise ModelError(
                    f"initial_models must be (M, {self.motion.n_params}), got {tuple(models.shape)}"
                )
            previous = self._plausible(models)
        tracker = ObjectTracker(self.motion, initial_objects, next_object_id)
        for batch in _batched(kept, batch_size):
            runs = [self._runs_level_one(window.index) for window in batch]
            results = segment([window.events for window in batch], previous, runs)
            if self.config.level_one.reuse_models:
                previous = self._plausible(results[-1].models)
            for window, result in zip(batch, results, strict=True):
                ids = tracker.update(result)
                yield replace(result, offset=window.offset, window_index=window.index, object_ids=ids)

    def _plausible(self, models: np.ndarray) -> np.ndarray:
        """The models worth reusing: a refit that diverged (no motion of this sensor) would only derail
        the next window."""
        return models[self.motion.plausible(models)]

    def _runs_level_one(self, index: int | None = None) -> bool:
        """Whether level one runs in a window that carries models in: not with ``replace``; with
        ``demand``, in a stream's window ``index`` only on every ``refresh_windows``-th window (a window's
        index, not the windows before, decides, so that a resumed stream runs it where the uninterrupted
        one did), and always in a window of one's own (``index`` ``None``)."""
        settings = self.config.level_one
        if settings.initial_models == "demand" and index is not None:
            return index % settings.refresh_windows == 0
        return settings.initial_models != "replace"

    def _segment(
        self, windows: list, initial_models, level_one: list[bool] | None = None
    ) -> list[Segmentation]:
        """:meth:`segment_batch` with every window starting from the same models."""
        return self.segment_batch(windows, None, [initial_models] * len(windows), level_one)

    def _result(
        self, prepared, batch: EventBatch, two, before_ms: float, level_two_ms: float, as_tensors: bool
    ):
        """One window's :class:`Segmentation` from its level-one and level-two results."""
        events, t_ref_us, tracks, fitted, features_ms = prepared
        with torch.no_grad():
            own = two.params[two.labels]
            warped = warp_events(self.motion, batch.xy[:, None], batch.t[:, None], own)[:, 0]
        labels, models, iwes, soft = two.labels, two.params, two.iwes, two.soft_assignments
        plain_models = _numpy(models).astype(np.float64)
        _, centres, boxes = describe_clusters(_numpy(labels), _numpy(warped), len(plain_models))
        if not as_tensors:
            labels, iwes, soft = _numpy(labels), _numpy(iwes), _numpy(soft)
            models, warped = plain_models, _numpy(warped).astype(np.float64)
        result = Segmentation(
            labels=labels,
            models=models,
            motion_model=self.config.motion_model,
            warped_xy=warped,
            t_ref=t_ref_us * 1e-6,
            feature_tracks=tracks,
            feature_labels=np.asarray(fitted.labels, dtype=np.int64),
            level_one_models=np.asarray(fitted.params, dtype=np.float64),
            iwes=iwes,
            soft_assignments=soft,
            energy_history=tuple(two.energy_history),
            timings_ms={
                "features": features_ms,
                "level_one": before_ms - features_ms,
                "level_two": level_two_ms,
                "total": before_ms + level_two_ms,
            },
            sensor_size=self.sensor_size,
            events=events,
            centres=centres,
            boxes=boxes,
            shared_motion=shared_motion_groups(
                plain_models, boxes, window_duration(events), self.motion, self.sensor_size
            ),
        )
        return replace(result, object_ids=ObjectTracker(self.motion).update(result))

    def _level_one(self, events: np.ndarray, t_ref_us: int, initial_models, runs: bool = True):
        """Features and Progressive-X; skipped in a window of one instant, on a tiny sensor, or where the
        window carries models in and ``runs`` is false (they are then level two's pool)."""
        cfg = self.config
        start = time.perf_counter()
        given = None if initial_models is None else self.motion.check_instances(initial_models)
        carried = _carries(given)
        replaced = carried and not runs
        if replaced or events["t"][-1] == events["t"][0] or min(self.sensor_size) < _MIN_FEATURE_SIZE:
            empty = np.zeros((0, 2))
            tracks = Correspondences(empty, empty, np.zeros(0), 0.0, 0.0)
            pool = given if replaced else np.zeros((0, self.motion.n_params))
            fitted = ProgressiveXResult(pool, np.zeros(0, dtype=np.int64), 0, 0)
            return tracks, fitted, 1e3 * (time.perf_counter() - start)
        guided = (
            {"motion": self.motion, "initial_models": initial_models} if cfg.features.guided_tracking else {}
        )
        tracks = extract_correspondences(
            events, self.sensor_size, t_ref=t_ref_us, **cfg.features.correspondence_settings(), **guided
        )
        after_features = time.perf_counter()
        settings = cfg.level_one.progressive_x_settings()

        def fit(threshold: float, models) -> ProgressiveXResult:
            # Seeded afresh for every window: a window's labels never depend on the calls before it.
            return progressive_x(
                tracks.src,
                tracks.dst,
                tracks.dt,
                self.motion,
                **{**settings, "threshold": threshold},
                initial_models=models,
                rng=np.random.default_rng(cfg.seed),
            )

        fitted = fit(settings["threshold"], initial_models)
        # Further runs at other thresholds only add hypotheses; the tracks keep the first run's labels. A
        # window that carries models in (a stream's) has hypotheses for its objects already, and there
        # the further runs' pools cost streamed detection (docs/objects.md).
        thresholds = () if carried else cfg.level_one.extra_thresholds
        extra = [fit(threshold, None).params for threshold in thresholds]
        if extra:
            fitted = replace(fitted, params=np.concatenate([fitted.params, *extra]))
        return tracks, fitted, 1e3 * (after_features - start)

    def _device_dtype(self) -> tuple[torch.device, torch.dtype]:
        return self._anchor.device, self._anchor.dtype


def _carries(models) -> bool:
    """Whether a window carries models in: a stream's windows after its first, or given ``initial_models``."""
    return models is not None and len(models) > 0


def _reference_us(events: np.ndarray, t_ref) -> int:
    if t_ref is None:
        t_ref_us = int(events["t"][0])
    elif isinstance(t_ref, bool) or not isinstance(t_ref, Real) or not math.isfinite(t_ref):
        raise EventFormatError(f"t_ref must be a finite time in seconds, got {t_ref!r}")
    else:
        t_ref_us = round(float(t_ref) * 1e6)
    # Event times are taken relative to t_ref in int64 microseconds, which must not wrap around.
    span = max(abs(int(events["t"][0]) - t_ref_us), abs(int(events["t"][-1]) - t_ref_us))
    if max(abs(t_ref_us), span) > _MAX_SPAN_US:
        raise EventFormatError(
            f"the events lie too far from t_ref = {t_ref_us * 1e-6} s for int64 microseconds"
        )
    return t_ref_us


def _as_chunks(events, sensor_size) -> Iterable[np.ndarray]:
    if isinstance(events, np.ndarray) or not isinstance(events, Iterable):
        return [as_events(events, sensor_size)]
    return (as_events(chunk, sensor_size) for chunk in events)


def _event_rows(events):
    """A tensor or an ``EventBatch`` as NumPy ``[t_seconds, x, y, p]`` rows; any other input as it is."""
    if isinstance(events, EventBatch):
        events = torch.column_stack([events.t.double(), events.xy.double(), events.p.double()])
    if isinstance(events, Tensor):
        return events.detach().cpu().double().numpy()
    return events


def _batched(items: Iterable, size: int) -> Iterator[list]:
    """Consecutive lists of ``size`` items (the last may be shorter), read one list at a time."""
    items = iter(items)
    while batch := list(itertools.islice(items, size)):
        yield batch


def _numpy(value):
    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
