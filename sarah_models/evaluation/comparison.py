"""Two evaluations of the same windows, compared window by window.

Each row of Table 1 carries 95 % intervals of its own, but two rows' intervals can overlap where
their difference is not in doubt: most of a row's spread is which windows were drawn, and two
models scored on the same windows share it. A paired comparison resamples the same units for
both rows and reads the interval of their difference (and ratio), as each row is already read
beside GT (``metrics.table.paired_comparison``):

* a Fréchet distance's Avg: the batches (batch b of both rows holds the same windows when they
  were scored with the same ``--batch-clips`` on the same windows), a paired bootstrap;
* its pooled distance: the jackknife's groups, each group's leave-one-out distance of one row
  less the other's, whose spread gives the difference's standard error (and the ratio's);
* a per-clip metric: the clips, a paired bootstrap.

Rows scored before the tables kept those units (``MetricsTable.per_batch`` and kin) cannot be
compared: they are refused by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .metrics import registered
from .metrics.table import MetricsTable, jackknife_spread, paired_comparison


class ComparisonError(ValueError):
    """Two tables that cannot be compared pair by pair, said in one line."""


@dataclass(frozen=True)
class Difference:
    """One figure of two rows: ``a``, ``b``, ``a - b`` and ``a / b`` with 95 % paired intervals
    (raw units, as ``MetricsTable.values``; NaN where there is none)."""

    name: str  # the metric's key: "fgd_acc", "fgd_acc@legs", "wrist_speed", ...
    column: str  # "avg" or "pooled"
    a: float
    b: float
    gap: float
    gap_low: float
    gap_high: float
    ratio: float = math.nan
    ratio_low: float = math.nan
    ratio_high: float = math.nan

    @property
    def separated(self) -> bool:
        """Whether the difference's interval leaves out 0."""
        return self.gap_low > 0 or self.gap_high < 0


def _check_comparable(a: MetricsTable, b: MetricsTable) -> None:
    if not (a.per_clip and b.per_clip):
        raise ComparisonError("a row without its per-window values (scored by a sarah-eval "
                              "older than the comparison); evaluate it again")
    if (a.num_clips, a.window_frames) != (b.num_clips, b.window_frames):
        raise ComparisonError(f"the rows are of different windows: {a.num_clips} and "
                              f"{b.num_clips} windows of {a.window_frames} and {b.window_frames} "
                              "frames")
    if a.batch_clips != b.batch_clips:
        raise ComparisonError(f"the rows' FGD batches differ ({a.batch_clips} and "
                              f"{b.batch_clips} clips): evaluate with the same --batch-clips")
    if a.shell_parts != b.shell_parts:
        raise ComparisonError("the rows split the shell into body parts differently (other "
                              "windows or shards)")


def _pooled(name: str, a: MetricsTable, b: MetricsTable) -> Difference:
    left_a, left_b = (np.asarray(t.per_group.get(name, []), dtype=np.float64) for t in (a, b))
    value_a, value_b = a.values[name].pooled, b.values[name].pooled
    gap, ratio = value_a - value_b, (value_a / value_b if value_b else math.nan)
    if len(left_a) != len(left_b) or len(left_a) == 0:
        return Difference(name, "pooled", value_a, value_b, gap, math.nan, math.nan, ratio)
    spread = jackknife_spread(left_a - left_b)
    ratio_spread = (jackknife_spread(left_a / left_b) if np.all(left_b != 0) else math.nan)
    return Difference(name, "pooled", value_a, value_b, gap, gap - spread, gap + spread,
                      ratio, ratio - ratio_spread, ratio + ratio_spread)


def _paired(name: str, values_a, values_b, ratio: bool) -> Difference:
    values_a, values_b = np.asarray(values_a, np.float64), np.asarray(values_b, np.float64)
    found = paired_comparison(values_a, values_b, ratio=ratio)
    return Difference(name, "avg", float(values_a.mean()), float(values_b.mean()),
                      **{k: found.get(k, math.nan) for k in ("gap", "gap_low", "gap_high", "ratio",
                                                              "ratio_low", "ratio_high")})


def compare(a: MetricsTable, b: MetricsTable) -> list[Difference]:
    """Every figure both rows hold, ``a`` against ``b``: each Fréchet distance's Avg and pooled
    value (the registered metrics', then FGD_acc's body parts'), then each per-clip metric's."""
    _check_comparable(a, b)
    out = []
    distances = [name for name in a.distances() if name in b.per_batch and name in a.per_batch]
    for name in distances:
        batches_a, batches_b = a.per_batch[name], b.per_batch[name]
        if len(batches_a) != len(batches_b):
            raise ComparisonError(f"{name}: {len(batches_a)} and {len(batches_b)} batches")
        out.append(_paired(name, batches_a, batches_b, ratio=True))
        out.append(_pooled(name, a, b))
    for metric in registered():
        if metric.kind == "clip" and metric.name in a.per_clip and metric.name in b.per_clip:
            out.append(_paired(metric.name, a.per_clip[metric.name], b.per_clip[metric.name],
                               ratio=metric.ratio_to_gt))
    return out


def label_of(name: str) -> str:
    """A figure's name as the tables write it: "FGD_acc", "FGD_acc, legs", "Wrist Var"."""
    metric, _, part = name.partition("@")
    found = next((m.label for m in registered() if m.name == metric), metric)
    return f"{found}, {part}" if part else found


def comparison_markdown(differences: list[Difference], table: MetricsTable, label_a: str,
                        label_b: str) -> str:
    """The differences as a markdown table, values as Table 1 shows them (``display_scale``)."""
    metrics = {m.name: m for m in registered()}
    lines = [f"| figure | {label_a} | {label_b} | difference (95 %) | ratio (95 %) | apart |",
             "|:---|---:|---:|---:|---:|:---:|"]
    for d in differences:
        metric = metrics[d.name.partition("@")[0]]
        scale = table.display_scale.get(d.name, metric.scale)
        decimals = metric.decimals

        def shown(value: float) -> str:
            return "-" if math.isnan(value) else f"{value / scale:,.{decimals}f}"

        # a per-clip difference is usually far smaller than the values: one more decimal
        places = decimals + (metric.kind == "clip")
        gap = (f"{d.gap / scale:+,.{places}f}" + ("" if math.isnan(d.gap_low) else
               f" ({d.gap_low / scale:+,.{places}f} to {d.gap_high / scale:+,.{places}f})"))
        ratio = ("-" if math.isnan(d.ratio) else f"{d.ratio:.2f}" + (
            "" if math.isnan(d.ratio_low) else f" ({d.ratio_low:.2f}-{d.ratio_high:.2f})"))
        column = " pooled" if d.column == "pooled" else ""
        name = label_of(d.name) + column + (" (Avg)" if metric.kind == "frechet"
                                            and d.column == "avg" else "")
        lines.append(f"| {name} | {shown(d.a)} | {shown(d.b)} | {gap} | {ratio} | "
                     f"{'yes' if d.separated else 'no'} |")
    return "\n".join(lines) + "\n"
