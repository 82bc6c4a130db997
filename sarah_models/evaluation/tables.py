"""Table 1 and Table 2 of the paper as markdown and JSON rows, and their plots.

Columns come from the metric registry (``metrics/spec.py``): label, arrow, display scale,
decimals and value range are each metric's own.
"""

from __future__ import annotations

import json
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from sarah_data.atomic import atomic_write_text
from sarah_data.constants import FPS

from ..generation.plots import save_figure
from .metrics import MetricsTable, registered
from .metrics.body_parts import SCORED_METRIC, part_key


@dataclass
class MethodResult:
    """One table row: a method's metrics and speed."""

    key: str  # "gt", "random", "nn", "model" or "model@<gaze>"
    label: str  # shown in the table
    causal: bool | None  # None: not applicable (GT)
    fps: float | None
    table: MetricsTable
    gaze: float | None = None
    reference: bool = False  # GT: FGD is "-"
    # pelvis floor paths (T, 2) of the windows plots/paths.png draws, by window index; empty for
    # a row that is not drawn (``paths.py``)
    floor_paths: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def realtime(self) -> bool | None:
        return None if self.fps is None else self.fps >= FPS

    def shown(self) -> dict[str, float | None]:
        """Displayed values (scaled), None where the table shows '-'."""
        row = self.table.to_row(scale=True)
        out = {k: (None if math.isnan(v) else float(v)) for k, v in row.items()}
        if self.reference:
            for key in out:
                if key.startswith("fgd"):
                    out[key] = None
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"key": self.key, "method": self.label, "causal": self.causal,
                "realtime": self.realtime, "fps": self.fps, "gaze": self.gaze,
                "reference": self.reference, "shown": self.shown(), "raw": self.table.to_dict()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "MethodResult":
        """A row ``to_dict`` wrote (one of table1.json's ``rows``); the plotted paths are not
        stored."""
        return cls(data["key"], data["method"], data["causal"], data["fps"],
                   MetricsTable.from_dict(data["raw"]), data["gaze"], stored_reference(data))


def stored_reference(row: dict[str, Any]) -> bool:
    """Whether a table1.json row is the reference (GT); rows from before "reference" was
    written: the "gt" row is."""
    return row.get("reference", row["key"] == "gt")


def read_table1_row(table1: Path | str, key: str | None = None) -> MethodResult:
    """The row ``key`` of a sarah-eval table1.json; None: the "model" row, or the only row that
    is not the reference (GT) when there is no model row (a ``--methods vae`` run); ValueError
    naming the file and the problem."""
    try:
        rows = json.loads(Path(table1).read_text())["rows"]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{table1}: not a sarah-eval table1.json ({exc})") from None
    keys = ", ".join(r["key"] for r in rows)
    if key is None:
        scored = [r["key"] for r in rows if not stored_reference(r)]
        if "model" not in scored and len(scored) != 1:
            raise ValueError(f"{table1}: no row 'model' and {len(scored)} others (rows: {keys}); "
                             f"name one as FOLDER:KEY")
        key = "model" if "model" in scored else scored[0]
    found = next((row for row in rows if row["key"] == key), None)
    if found is None:
        raise ValueError(f"{table1}: no row {key!r} (rows: {keys})")
    return MethodResult.from_dict(found)


def fps_of(seconds: Sequence[float], frames: int) -> float | None:
    return frames / max(statistics.median(seconds), 1e-12) if seconds else None


def gaze_label(g: float | None) -> str:
    return "∅" if g is None else f"{g:.1f}"


# --------------------------------------------------------------------------- formatting


def number(value: float | None, decimals: int) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{decimals}f}"


def _mark(flag: bool | None) -> str:
    return "-" if flag is None else ("✓" if flag else "✗")


def _scale_note(scale: float) -> str:
    if scale == 1.0:
        return ""
    exponent = math.log10(scale)
    return f" (×10^{int(round(exponent))})" if abs(exponent - round(exponent)) < 1e-9 else f" (×{scale:g})"


def metric_header(name: str, scale: float) -> str:
    metric = next(m for m in registered() if m.name == name)
    return f"{metric.label} {metric.arrow}{_scale_note(scale)}{metric.value_range}"


def scored(rows: Sequence[MethodResult]) -> list:
    """The registered metrics the rows hold values of, in column order."""
    return [m for m in registered() if m.name in rows[0].table.values]


def interval(shown: dict, name: str, decimals: int,
             columns: tuple[str, str, str] = ("avg", "low", "high")) -> str:
    """A value with its 95 % interval, "0.58 (0.55-0.61)" (Avg by default; ``columns`` names
    another, e.g. pooled); the value alone where there is no interval."""
    return with_interval(*(shown.get(f"{name}/{k}") for k in columns), decimals)


def with_interval(value: float | None, low: float | None, high: float | None,
                  decimals: int) -> str:
    """"0.58 (0.55-0.61)"; the value alone where either end is missing (None or NaN)."""
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in (low, high)):
        return number(value, decimals)
    return f"{number(value, decimals)} ({number(low, decimals)}-{number(high, decimals)})"


def table1_markdown(rows: Sequence[MethodResult], caption: str) -> str:
    """Table 1 as markdown: Method, C, R, FPS, then every metric as Avg (95 % interval) and
    NS/S, and for the Fréchet metrics the distance over all clips pooled (95 % interval)."""
    scale, metrics = rows[0].table.display_scale, scored(rows)
    head = ["Method", "C", "R", "FPS"]
    for metric in metrics:
        head += [f"{metric_header(metric.name, scale[metric.name])} Avg (95 %)", "NS/S"]
        if metric.kind == "frechet":
            head.append("Pooled (95 %)")
    lines = [f"**{caption}**", "", "| " + " | ".join(head) + " |",
             "|" + "|".join([":---"] + [":---:"] * (len(head) - 1)) + "|"]
    for row in rows:
        shown = row.shown()
        cells = [row.label, _mark(row.causal), _mark(row.realtime),
                 "-" if row.fps is None else f"{row.fps:.0f}"]
        for metric in metrics:
            name, d = metric.name, metric.decimals
            cells += [interval(shown, name, d),
                      f"{number(shown[f'{name}/ns'], d)}/{number(shown[f'{name}/s'], d)}"]
            if metric.kind == "frechet":
                cells.append(interval(shown, name, d, ("pooled", "pooled_low", "pooled_high")))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n" + beside_gt_markdown(rows) + parts_markdown(rows)


def beside_gt_markdown(rows: Sequence[MethodResult]) -> str:
    """Each scored row's per-clip metrics against GT's on the same windows: the difference of
    the means and (``ratio_to_gt``) their ratio, each with its paired 95 % bootstrap interval;
    "" when no row has them (GT alone, or tables from before they were computed)."""
    metrics = [m for m in scored(rows) if m.kind == "clip"] if rows else []
    scored_rows = [r for r in rows if not r.reference
                   and any(r.shown().get(f"{m.name}/gap") is not None for m in metrics)]
    if not scored_rows:
        return ""
    head = ["Method"] + [f"{m.label} − GT" + ("; ÷ GT" if m.ratio_to_gt else "") for m in metrics]
    lines = ["", "**Beside GT on the same windows: difference (this − GT) and, for magnitudes, "
             "ratio (this ÷ GT) of the means, paired 95 % bootstrap intervals.**", "",
             "| " + " | ".join(head) + " |", "|" + "|".join([":---"] + [":---:"] * len(metrics)) + "|"]
    for row in scored_rows:
        shown, cells = row.shown(), [row.label]
        for metric in metrics:
            gap, low, high = (shown.get(f"{metric.name}/{k}") for k in ("gap", "gap_low", "gap_high"))
            d = metric.decimals + 1
            cell = "-" if gap is None else f"{gap:+.{d}f} ({low:+.{d}f} to {high:+.{d}f})"
            if shown.get(f"{metric.name}/ratio") is not None:
                cell += f"; {interval(shown, metric.name, 2, ('ratio', 'ratio_low', 'ratio_high'))}×"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def part_rows(rows: Sequence[MethodResult]) -> tuple[list[MethodResult], dict[str, int]]:
    """The rows scored by body part (every row but GT's, from a sarah-eval that scores parts)
    and the shell points of each part, by the first such row."""
    scored_rows = [r for r in rows if not r.reference and r.table.shell_parts]
    points = ({part: len(indices) for part, indices in scored_rows[0].table.shell_parts.items()}
              if scored_rows else {})
    return scored_rows, points


def parts_markdown(rows: Sequence[MethodResult]) -> str:
    """FGD_acc of the whole shell and of each body part's shell points (``metrics.body_parts``),
    Avg with its 95 % bootstrap interval, and each part's acceleration energy ÷ GT's on the same
    windows with its paired 95 % interval; "" when no row has parts."""
    scored_rows, points = part_rows(rows)
    if not scored_rows:
        return ""
    metric = next(m for m in registered() if m.name == SCORED_METRIC)
    header = metric_header(metric.name, scored_rows[0].table.display_scale[metric.name])
    head = ["Method", f"whole shell ({sum(points.values())})"] + [
        f"{part} ({count})" for part, count in points.items()]
    lines = ["", f"**{header} by body part (the shell points nearest each part's joints in the "
             "first window; points in brackets): Avg (95 % bootstrap); e = acceleration energy "
             "÷ GT's on the same windows (paired 95 %).**", "",
             "| " + " | ".join(head) + " |", "|" + "|".join([":---"] + [":---:"] * (len(head) - 1)) + "|"]
    for row in scored_rows:
        shown = row.shown()
        cells = [row.label, interval(shown, metric.name, metric.decimals)]
        for part in points:
            key = part_key(part)
            cells.append(f"{interval(shown, key, metric.decimals)}; e "
                         f"{interval(shown, key, 2, ('ratio', 'ratio_low', 'ratio_high'))}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table2_markdown(rows: Sequence[MethodResult], caption: str) -> str:
    """Table 2 as markdown: one row per gaze target g with every metric's Avg."""
    scale = rows[0].table.display_scale
    head = ["g"] + [metric_header(m.name, scale[m.name]) for m in scored(rows)]
    lines = [f"**{caption}**", "", "| " + " | ".join(head) + " |",
             "|" + "|".join([":---"] + [":---:"] * (len(head) - 1)) + "|"]
    for row in rows:
        shown = row.shown()
        lines.append("| " + " | ".join([gaze_label(row.gaze)] + [
            number(shown[f"{m.name}/avg"], m.decimals) for m in scored(rows)]) + " |")
    return "\n".join(lines) + "\n"


def write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, ensure_ascii=False, allow_nan=False) + "\n")


# --------------------------------------------------------------------------- plots


def plot_metric_bars(folder: Path, rows: Sequence[MethodResult]) -> list[Path]:
    """One PNG per metric: Avg, NS and S of every method (displayed units); GT's Avg dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    scale = rows[0].table.display_scale
    for name in (m.name for m in scored(rows)):
        fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(rows), 3.6))
        x = np.arange(len(rows))
        for k, (column, colour) in enumerate((("avg", "tab:blue"), ("ns", "tab:gray"),
                                              ("s", "tab:orange"))):
            values = [row.shown()[f"{name}/{column}"] for row in rows]
            heights = [np.nan if v is None else v for v in values]
            ax.bar(x + (k - 1) * 0.27, heights, width=0.27, color=colour,
                   label={"avg": "Avg", "ns": "NS", "s": "S"}[column])
        gt = next((r for r in rows if r.reference), None)
        if gt is not None and gt.shown()[f"{name}/avg"] is not None:
            ax.axhline(gt.shown()[f"{name}/avg"], color="k", ls="--", lw=1, label="GT Avg")
        ax.set_xticks(x, [row.label for row in rows], rotation=20, ha="right")
        ax.set_title(metric_header(name, scale[name]))
        ax.legend(fontsize=7)
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        paths.append(save_figure(fig, folder / f"metric_{name}.png"))
    return paths


def plot_parts(path: Path, rows: Sequence[MethodResult]) -> Path | None:
    """FGD_acc Avg of the whole shell and of each body part (x) for every row scored by part,
    with its 95 % bootstrap interval, on a log scale (a part's distance spans decades from the
    real floor to a raw decoder); None when no row has parts."""
    scored_rows, points = part_rows(rows)
    if not scored_rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [SCORED_METRIC] + [part_key(part) for part in points]
    labels = [f"whole shell\n({sum(points.values())})"] + [
        f"{part}\n({count})" for part, count in points.items()]
    fig, ax = plt.subplots(figsize=(2.0 + 1.2 * len(keys),
                                    4.4 + 0.2 * ((len(scored_rows) + 2) // 3)))  # legend rows
    width = 0.8 / len(scored_rows)
    x = np.arange(len(keys))
    for k, row in enumerate(scored_rows):
        shown = row.shown()
        avg, low, high = (np.array([np.nan if shown.get(f"{key}/{c}") is None else shown[f"{key}/{c}"]
                                    for key in keys]) for c in ("avg", "low", "high"))
        ax.bar(x + (k - (len(scored_rows) - 1) / 2) * width, avg, width=width, label=row.label,
               yerr=np.stack([avg - low, high - avg]), capsize=2, error_kw={"lw": 0.8})
    ax.set_yscale("log")
    ax.set_xticks(x, labels, fontsize=8)
    metric = next(m for m in registered() if m.name == SCORED_METRIC)
    ax.set_ylabel(f"{metric_header(metric.name, scored_rows[0].table.display_scale[metric.name])}"
                  " Avg (95 %)")
    ax.set_title("FGD_acc by body part (shell points per part)")
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16),
              ncol=min(3, len(scored_rows)))  # below the axes: bars reach every corner
    fig.tight_layout()
    return save_figure(fig, path)


def plot_gaze_control(path: Path, sweep: Sequence[MethodResult], gt_head: float | None) -> Path:
    """Target gaze g (x) against achieved Head Ang. Avg (y); GT dashed, ∅ dotted, y = x faint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.8, 4.0))
    points = sorted((r.gaze, r.shown()["head_angle/avg"]) for r in sweep if r.gaze is not None)
    if points:
        ax.plot([p[0] for p in points], [p[1] for p in points], "o-", color="tab:red",
                label="model (gaze control)")
    none = next((r for r in sweep if r.gaze is None), None)
    if none is not None:
        ax.axhline(none.shown()["head_angle/avg"], color="tab:red", ls=":", lw=1.2,
                   label="model, no gaze control (∅)")
    if gt_head is not None:
        ax.axhline(gt_head, color="k", ls="--", lw=1.2, label="GT")
    ax.plot([-1, 1], [-1, 1], color="0.8", lw=0.8, zorder=0, label="achieved = target")
    ax.set_xlim(-0.05, 1.05)
    ax.set_xlabel("target gaze score g")
    ax.set_ylabel("achieved Head Ang. (Avg)")
    ax.set_title("Gaze control (Table 2)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return save_figure(fig, path)


