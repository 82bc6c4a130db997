"""Scoring clips with every registered metric, three ways: Avg, NS (non-speaking), S (speaking).

* Fréchet metrics (FGD, FGD_acc): S and NS are one Fréchet distance each between the pooled
  generated and pooled ground-truth samples of that category; Avg is the mean of per-batch
  Fréchet distances over consecutive batches of ``batch_clips`` clips (all categories mixed),
  the paper's protocol. Small batches bias the covariance, so Avg is not a combination of S and
  NS and usually exceeds both; ``pooled`` is one distance over every clip, the figure that can
  tell methods apart. Avg's 95 % interval bootstraps the batch values; pooled's is a
  delete-one-group jackknife (``pooled_interval``), generated and ground-truth clips left out
  together. With ``MetricsConfig.shell_parts`` FGD_acc is scored on each body part's shell
  points too, the same way (``body_parts``), with the part's acceleration energy ÷ GT's.
* Per-clip metrics (foot slide, wrist speed, head angle): one value per generated clip; S and
  NS are the means over the clips of each category; Avg is their clip-count-weighted mean, with
  a 95 % bootstrap interval over clips; beside GT on the same windows, the difference of the
  means (and their ratio, for a metric with ``ratio_to_gt``) with paired 95 % bootstrap
  intervals (``paired_comparison``).

Reported values are in centimetres (the paper's meshes are in centimetres, and its thresholds
and table magnitudes read naturally in them); "FGD (x10^1)" in the paper's table header is read
as "shown in units of 10^1": shown = raw / 10.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from sarah_data.moments import Moments

from .body_parts import SCORED_METRIC, energy, part_key, part_samples
from .clips import Clip, DecodedClip, as_numpy
from .frechet import moments_distance
from .spec import MetricsConfig, registered, unit_name


@dataclass
class CategoryValues:
    """One metric's Avg, NS and S values (NaN where a category has no clips), the 95 %
    bootstrap interval of Avg (``low``, ``high``), the value over all clips pooled and, for a
    Fréchet metric, its 95 % jackknife interval (``pooled_low``, ``pooled_high``)."""

    avg: float
    ns: float
    s: float
    low: float = math.nan
    high: float = math.nan
    pooled: float = math.nan
    pooled_low: float = math.nan
    pooled_high: float = math.nan
    # A per-clip metric beside the ground truth of the same windows: the difference of the
    # means (this minus GT) and, for a magnitude (``Metric.ratio_to_gt``), their ratio, each
    # with a 95 % paired bootstrap interval. The acceptance targets are of this form ("within
    # 0.05 of GT", "within 20 % of GT"), and pairing cancels the spread the windows share,
    # which two separate intervals count twice.
    gap: float = math.nan
    gap_low: float = math.nan
    gap_high: float = math.nan
    ratio: float = math.nan
    ratio_low: float = math.nan
    ratio_high: float = math.nan


BOOTSTRAP_DRAWS = 1000
UNSCALED_COLUMNS = ("ratio", "ratio_low", "ratio_high")  # no unit: the display scale cancels


def bootstrap_interval(values, seed: int = 0, draws: int = BOOTSTRAP_DRAWS) -> tuple[float, float]:
    """95 % percentile-bootstrap interval of the mean of ``values`` (resampled with
    replacement, ``draws`` times, from a fixed seed)."""
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = values[rng.integers(len(values), size=(draws, len(values)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)


def paired_comparison(values, reference, ratio: bool = True, seed: int = 0,
                      draws: int = BOOTSTRAP_DRAWS) -> dict[str, float]:
    """``values`` against ``reference``, clip i of each from the same window: the difference of
    their means and (with ``ratio``) their ratio, each with its 95 % percentile-bootstrap
    interval, both means of every draw taken over the same resampled windows (no ratio where
    GT's mean is 0; the ratio's interval from the draws whose GT mean is not 0: a few windows
    where a part stands perfectly still now and then draw only such windows)."""
    values = np.asarray(values, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if len(values) == 0 or values.shape != reference.shape:
        return {}
    rng = np.random.default_rng(seed)
    picks = rng.integers(len(values), size=(draws, len(values)))
    means, gt_means = values[picks].mean(axis=1), reference[picks].mean(axis=1)
    out = {"gap": float(values.mean() - reference.mean())}
    out["gap_low"], out["gap_high"] = (float(v) for v in np.percentile(means - gt_means, [2.5, 97.5]))
    if ratio and reference.mean() != 0:
        defined = gt_means != 0
        out["ratio"] = float(values.mean() / reference.mean())
        out["ratio_low"], out["ratio_high"] = (float(v) for v in np.percentile(
            means[defined] / gt_means[defined], [2.5, 97.5]))
    return out


def left_out_distances(groups: Sequence[tuple[Moments, Moments]], ridge: float) -> list[float]:
    """The delete-one-group jackknife's distances: ``groups`` holds each group's (generated,
    ground-truth) moments; group g's value is the Fréchet distance over every other group, both
    sides left out together."""
    left_out = []
    for skip in range(len(groups)):
        rest = [Moments(full=True), Moments(full=True)]
        for g, pair in enumerate(groups):
            if g != skip:
                for side, moments in zip(rest, pair):
                    side.merge(moments)
        left_out.append(moments_distance(rest[0], rest[1], ridge))
    return left_out


def jackknife_spread(left_out) -> float:
    """1.96 jackknife standard errors, 1.96 sqrt((G - 1) / G * sum (d_g - mean d)^2), of a
    statistic whose leave-one-group-out values are ``left_out``; NaN with fewer than 3 groups
    or a non-finite value."""
    values = np.asarray(left_out, dtype=np.float64)
    if len(values) < 3 or not np.all(np.isfinite(values)):
        return math.nan
    return 1.96 * math.sqrt((len(values) - 1) / len(values) * np.sum((values - values.mean()) ** 2))


def pooled_interval(left_out: Sequence[float], pooled: float) -> tuple[float, float]:
    """95 % interval of the Fréchet distance over all clips from its delete-one-group jackknife
    (``left_out_distances``): ``pooled`` +- ``jackknife_spread``, its low end at least 0 (a
    distance is not negative). NaN with fewer than 3 groups (or of two samples each)."""
    spread = jackknife_spread(left_out)
    if math.isnan(spread):
        return math.nan, math.nan
    return max(pooled - spread, 0.0), pooled + spread


@dataclass
class MetricsTable:
    """Raw metric values (in `units`) with the counts and settings that produced them."""

    values: dict[str, CategoryValues]
    units: dict[str, str]
    display_scale: dict[str, float]
    num_clips: int
    num_speaking: int
    num_non_speaking: int
    window_frames: int
    fps: float
    batch_clips: int
    num_batches: int
    # FGD_acc by body part (``body_parts``): the shell point indices each part's values (under
    # ``part_key(part)`` in ``values``) were scored on; empty when parts were not scored.
    shell_parts: dict[str, list[int]] = field(default_factory=dict)
    # What the intervals resampled, in ``values``' units, so that two evaluations of the same
    # windows can be compared pair by pair (``evaluation.comparison``), which two separate
    # intervals cannot: each Fréchet distance's batch values (``per_batch``, Avg's bootstrap)
    # and leave-one-group-out distances (``per_group``, pooled's jackknife), each per-clip
    # metric's clip values (``per_clip``, in window order). Empty in files from before them.
    per_batch: dict[str, list[float]] = field(default_factory=dict)
    per_group: dict[str, list[float]] = field(default_factory=dict)
    per_clip: dict[str, list[float]] = field(default_factory=dict)

    def distances(self) -> list[str]:
        """The keys of the Fréchet distances in ``values``: the registered metrics', then the
        parts'."""
        return ([m.name for m in registered() if m.kind == "frechet" and m.name in self.values]
                + [part_key(part) for part in self.shell_parts])

    def to_row(self, scale: bool = True) -> dict[str, float]:
        """{"fgd/avg": ..., "fgd/ns": ..., "fgd/s": ..., ...}; scale=True divides by the table's
        display factors (FGD / 10, FGD_acc / 1e5), as the paper's Table 1 shows them."""
        row = {}
        for name in self.values:
            factor = self.display_scale[name] if scale else 1.0
            for column, value in asdict(self.values[name]).items():
                row[f"{name}/{column}"] = value if column in UNSCALED_COLUMNS else value / factor
        return row

    def to_dict(self) -> dict:
        """JSON-ready, raw (unscaled) values; NaN becomes None."""
        out = asdict(self)
        out["values"] = {name: {k: (None if math.isnan(v) else v) for k, v in values.items()}
                         for name, values in out["values"].items()}
        for kept in ("per_batch", "per_group", "per_clip"):
            out[kept] = {name: [None if math.isnan(v) else v for v in values]
                         for name, values in out[kept].items()}
        return out

    @classmethod
    def from_dict(cls, data: Mapping) -> "MetricsTable":
        """The table ``to_dict`` wrote (a table1.json row's ``raw``): None back to NaN."""
        fields = dict(data)
        fields["values"] = {name: CategoryValues(**{k: math.nan if v is None else v
                                                    for k, v in values.items()})
                            for name, values in data["values"].items()}
        for kept in ("per_batch", "per_group", "per_clip"):
            fields[kept] = {name: [math.nan if v is None else v for v in values]
                            for name, values in data.get(kept, {}).items()}
        return cls(**fields)


def category_means(per_clip: np.ndarray, speaking: np.ndarray) -> CategoryValues:
    """Avg, NS and S of a per-clip metric: Avg is the mean over all clips, i.e. the clip-count
    weighted mean of the NS and S means (NaN for a category without clips)."""
    ns, s = (float(per_clip[speaking == cat].mean()) if np.any(speaking == cat) else math.nan
             for cat in (False, True))
    avg = float(per_clip.mean())
    return CategoryValues(avg, ns, s, *bootstrap_interval(per_clip), pooled=avg)


def metric_units(report_unit: float) -> dict[str, str]:
    unit = unit_name(report_unit)
    return {m.name: m.unit.format(u=unit) for m in registered()}


def _check_like(kind: str, index: int, clip: Clip, reference: Clip) -> None:
    if (clip.num_frames, clip.fps, clip.shell.shape[1]) != (
            reference.num_frames, reference.fps, reference.shell.shape[1]):
        raise ValueError(f"evaluate: {kind} clip {index} has {clip.num_frames} frames at {clip.fps} fps "
                         f"with {clip.shell.shape[1]} shell points; generated clip 0 has "
                         f"{reference.num_frames} at {reference.fps} with {reference.shell.shape[1]}")


def _table(values: dict[str, CategoryValues], cfg: MetricsConfig, speaking: np.ndarray,
           reference: Clip, num_batches: int, parts: Mapping[str, Sequence[int]] | None = None,
           **kept: dict[str, list[float]]) -> MetricsTable:
    parts = parts or {}
    units, scale = metric_units(cfg.report_unit), dict(cfg.display_scale)
    for part in parts:  # a part's FGD_acc reads as FGD_acc's
        units[part_key(part)], scale[part_key(part)] = units[SCORED_METRIC], scale[SCORED_METRIC]
    return MetricsTable(
        values=values, units=units, display_scale=scale,
        num_clips=len(speaking), num_speaking=int(speaking.sum()),
        num_non_speaking=int((~speaking).sum()), window_frames=reference.num_frames,
        fps=float(reference.fps), batch_clips=cfg.batch_clips, num_batches=num_batches,
        shell_parts={part: [int(p) for p in points] for part, points in parts.items()},
        **{name: {metric: [float(v) for v in values] for metric, values in by_metric.items()}
           for name, by_metric in kept.items()})


def evaluate(generated: Sequence[Clip], ground_truth: Sequence[Clip], speaking,
             batch_clips: int | None = None, config: MetricsConfig | None = None,
             reference_values: Mapping[str, np.ndarray] | None = None) -> MetricsTable:
    """Score generated clips against their ground truth (clip i of each is the same window).

    speaking (N,) bool: whether clip i is a speaking clip (sarah_data.speaking's clip rule on the
    agent's audio). FGD batches are consecutive runs of `batch_clips` clips in the given order;
    the last batch may be shorter. Per-clip metrics are scored on the generated clips and
    compared with the same metric on their ground truth (``paired_comparison``);
    ``reference_values`` (``clip_values`` of the ground truth) spares computing those again for
    every method scored against the same windows.
    The clip sequences may be lazy (any __len__/__getitem__); each clip is read once, in order.
    All clips must share one length, frame rate and shell size.
    """
    cfg = config or MetricsConfig()
    if batch_clips is not None:
        cfg = replace(cfg, batch_clips=batch_clips)
    if cfg.batch_clips < 1:
        raise ValueError(f"evaluate: batch_clips must be positive, got {cfg.batch_clips}")
    if cfg.pooled_groups < 0:
        raise ValueError(f"evaluate: pooled_groups must be >= 0, got {cfg.pooled_groups}")
    speaking = np.asarray(as_numpy(speaking)).astype(bool).reshape(-1)
    if len(generated) != len(ground_truth) or len(generated) != len(speaking) or len(generated) == 0:
        raise ValueError(f"evaluate: {len(generated)} generated clips, {len(ground_truth)} ground-truth "
                         f"clips and {len(speaking)} speaking flags; need equal, non-zero counts")
    reference = generated[0]
    parts = dict(cfg.shell_parts or {})
    points = reference.shell.shape[1]
    for part, indices in parts.items():
        if not indices or min(indices) < 0 or max(indices) >= points:
            raise ValueError(f"evaluate: shell part {part!r} names points outside the clips' "
                             f"{points} shell points")
    frechet = [m for m in registered() if m.kind == "frechet"]
    distances = [m.name for m in frechet] + [part_key(part) for part in parts]
    per_clip = {m.name: [] for m in registered() if m.kind == "clip"}
    gt_per_clip = {m.name: [] for m in registered() if m.kind == "clip"}
    energies = {(part, role): [] for part in parts for role in ("gen", "gt")}
    pooled = {(name, role, cat): Moments(full=True) for name in distances
              for role in ("gen", "gt") for cat in (False, True)}
    batch_values: dict[str, list[float]] = {name: [] for name in distances}
    group_count = min(cfg.pooled_groups, len(generated))
    groups = {name: [(Moments(full=True), Moments(full=True)) for _ in range(group_count)]
              for name in distances}
    for start in range(0, len(generated), cfg.batch_clips):
        batch = {(name, role): Moments(full=True) for name in distances for role in ("gen", "gt")}
        for i in range(start, min(start + cfg.batch_clips, len(generated))):
            for role, clip in (("gen", generated[i]), ("gt", ground_truth[i])):
                _check_like("generated" if role == "gen" else "ground-truth", i, clip, reference)
                decoded = DecodedClip(clip, cfg.root_joint, cfg.normalize_window)
                samples = {metric.name: metric.function(decoded, cfg) for metric in frechet}
                for part, values in part_samples(samples[SCORED_METRIC], parts).items():
                    samples[part_key(part)] = values
                    energies[part, role].append(energy(values))
                for name, values in samples.items():
                    moments = Moments(full=True)
                    moments.add(values)
                    batch[name, role].merge(moments)
                    pooled[name, role, bool(speaking[i])].merge(moments)
                    if group_count:  # consecutive clips, the groups as equal as they go
                        groups[name][i * group_count // len(generated)][role == "gt"].merge(moments)
                if role == "gen" or reference_values is None:
                    _add_clip_values(per_clip if role == "gen" else gt_per_clip, decoded, cfg)
        for name in distances:
            batch_values[name].append(moments_distance(batch[name, "gen"], batch[name, "gt"],
                                                       cfg.fd_ridge))

    def distance_values(name: str, factor: float) -> CategoryValues:
        ns, s = (moments_distance(pooled[name, "gen", cat], pooled[name, "gt", cat], cfg.fd_ridge)
                 for cat in (False, True))
        everything = {role: Moments(full=True) for role in ("gen", "gt")}
        for role in everything:
            for cat in (False, True):
                everything[role].merge(pooled[name, role, cat])
        batches = np.asarray(batch_values[name]) * factor
        low, high = bootstrap_interval(batches)
        whole = moments_distance(everything["gen"], everything["gt"], cfg.fd_ridge) * factor
        left_out = np.asarray(left_out_distances(groups[name], cfg.fd_ridge)) * factor
        per_batch[name], per_group[name] = list(batches), list(left_out)
        return CategoryValues(float(batches.mean()), ns * factor, s * factor, low, high,
                              whole, *pooled_interval(left_out, whole))

    gt_values = gt_per_clip if reference_values is None else reference_values
    length = 1.0 / cfg.report_unit  # metres -> reported unit
    values = {}
    per_batch: dict[str, list[float]] = {}
    per_group: dict[str, list[float]] = {}
    kept_clips: dict[str, list[float]] = {}
    for metric in registered():
        factor = length ** metric.length_power
        if metric.kind == "frechet":
            values[metric.name] = distance_values(metric.name, factor)
        else:
            clips = np.asarray(per_clip[metric.name]) * factor
            kept_clips[metric.name] = list(clips)
            values[metric.name] = replace(
                category_means(clips, speaking),
                **paired_comparison(clips, np.asarray(gt_values[metric.name]) * factor,
                                    ratio=metric.ratio_to_gt))
    scored = next(m for m in frechet if m.name == SCORED_METRIC)
    for part in parts:  # the distance, and the part's energy ÷ GT's (a ratio: no unit)
        energy_ratio = paired_comparison(energies[part, "gen"], energies[part, "gt"])
        values[part_key(part)] = replace(
            distance_values(part_key(part), length ** scored.length_power),
            **{k: v for k, v in energy_ratio.items() if k in UNSCALED_COLUMNS})
    return _table(values, cfg, speaking, reference, -(-len(generated) // cfg.batch_clips), parts,
                  per_batch=per_batch, per_group=per_group, per_clip=kept_clips)


def _add_clip_values(per_clip: dict[str, list[float]], decoded: DecodedClip,
                     cfg: MetricsConfig) -> None:
    for metric in registered():
        if metric.kind == "clip":
            per_clip[metric.name].append(metric.function(decoded, cfg))


def clip_values(clips: Sequence[Clip], config: MetricsConfig = MetricsConfig()) -> dict[str, np.ndarray]:
    """Every per-clip metric of every clip, raw (metres and seconds), in clip order."""
    per_clip: dict[str, list[float]] = {m.name: [] for m in registered() if m.kind == "clip"}
    for i in range(len(clips)):
        _add_clip_values(per_clip, DecodedClip(clips[i], config.root_joint, config.normalize_window),
                         config)
    return {name: np.asarray(values, dtype=np.float64) for name, values in per_clip.items()}


def reference_table(clips: Sequence[Clip], speaking: np.ndarray,
                    config: MetricsConfig = MetricsConfig(),
                    per_clip: Mapping[str, np.ndarray] | None = None) -> MetricsTable:
    """The GT row: the per-clip metrics of real motion (``per_clip``, when ``clip_values`` of
    ``clips`` is at hand) with the same S/NS pooling as ``evaluate`` and the Fréchet metrics NaN
    -- FGD of the ground truth against itself is 0 by definition, and computing it would only
    measure the covariance square root's rounding."""
    speaking = np.asarray(speaking, bool)
    per_clip = clip_values(clips, config) if per_clip is None else per_clip
    length = 1.0 / config.report_unit
    values, kept_clips = {}, {}
    for metric in registered():
        if metric.kind == "frechet":
            values[metric.name] = CategoryValues(math.nan, math.nan, math.nan)
        else:
            kept_clips[metric.name] = np.asarray(per_clip[metric.name]) * length ** metric.length_power
            values[metric.name] = category_means(kept_clips[metric.name], speaking)
    return _table(values, config, speaking, clips[0], 0, per_clip=kept_clips)
