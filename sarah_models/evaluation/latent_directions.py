"""Latent directions: how the flow's samples fill the directions of its VAE's latent space.

The flow learns the frozen encoder's latents standardized channel by channel, and Table 1 scores
only what the decoder makes of its samples. Between the two, nothing said whether a sample sits
where the data's latents sit: a flow can fill a direction too little (motion the data has, gone)
or too much, or move along it from token to token faster than the data does (jitter the decoder
then smooths, or passes on). The channels are no axes to read this on: they are correlated, and
on the fixture benchmark's tiny VAE a handful of directions hold nearly all the variance.

So the axes are the principal directions of the data's latents (the encoder means of the
evaluated windows, standardized as the flow sees them), ordered by the variance they hold. Per
direction k, with p the projection on it about the data's mean:

* share: the direction's share of the data's latent variance;
* spread: the samples' mean p² ÷ the data's (1: filled as the data fills it; a sample's mean
  away from the data's counts too);
* change: the mean squared token-to-token step of p ÷ twice the data's mean p² (0: the same value
  all window long; 1: neighbouring tokens uncorrelated), for the data and, in the data's units,
  for the samples, so that a sample jittering along a direction the data barely uses scores high.

The directions are grouped in bands by the data's cumulative variance (those holding the first
90 %, the next 9 %, the last 1 %); each band's spread and change ratio carry a 95 % paired
bootstrap interval over windows (``metrics.table.paired_comparison``; the directions are fixed
by all windows). The participation ratio, (sum of eigenvalues)² ÷ sum of their squares, says how
many directions each set of latents effectively fills.

Where the body stands is in some of these directions and not others. Given the pelvis's floor
position (x, z) per token of each window, every direction gets the R² of a line fit of that
position on it alone, and the directions whose R² reaches ``PLACEMENT_R2`` make one more row,
"placement": how the samples fill the directions that place the body (pooled FGD reads where
the body stands, but more than the pelvis: on the fixture benchmark this row did not follow it
from model to model, docs/results.md, fifty-ninth run).

How the body steps is in other directions still, and spread over many: no one direction explains
much of a token's step (the pelvis's floor position less the token's before it), but together
they do. So the "steps" row is a plane, not a set of principal directions: the two directions of
a ridge fit of each token's step on its latents (fitted on the data's, ``step_plane``), with
the fit's R² beside it and the samples' spread there against the data's. On the fixture
benchmark's root-step VAE (``vae.root_steps``) the plane holds 0.4 % of the latents' variance and
explains 0.72 of the steps, and that run's flow filled it at 0.76 of the data's spread
(docs/results.md, eighty-seventh run): a direction the flow's loss, weighing every channel alike,
barely sees.

``scripts/motion_anatomy.py`` reads the same latents along the other axis, by frequency band of
the token rate, channel by channel.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from sarah_data.skeleton import ROOT

from .metrics.table import paired_comparison
from .tables import with_interval

BANDS = (0.90, 0.99)  # cumulative data variance at which a band ends; the last band takes the rest
PLACEMENT_R2 = 0.05  # a direction carries placement when it alone explains this much of it
STEP_RIDGE = 1e-2  # the step plane's ridge, a share of the latents' mean variance per direction:
# enough to keep directions the data barely uses out of the fit


def principal_axes(latents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, K, D) latents -> (mean (D,), eigenvalues (D,) descending, directions (D, D) as columns)
    of their covariance over every window's every token."""
    flat = np.asarray(latents, np.float64).reshape(-1, latents.shape[-1])
    mean = flat.mean(0)
    values, vectors = np.linalg.eigh(np.cov(flat, rowvar=False))
    order = np.argsort(values)[::-1]
    return mean, np.clip(values[order], 0.0, None), vectors[:, order]


def participation(values: np.ndarray) -> float:
    """How many directions a covariance's eigenvalues effectively fill: (sum)² ÷ sum of squares."""
    values = np.asarray(values, np.float64)
    total = float((values ** 2).sum())
    return float(values.sum() ** 2 / total) if total > 0 else 0.0


def band_edges(shares: np.ndarray, bands: tuple[float, ...] = BANDS) -> list[tuple[int, int]]:
    """[start, end) direction ranges: the directions up to each cumulative share in ``bands``,
    then the rest; empty ranges are dropped."""
    cumulative = np.cumsum(shares)
    ends = [int(np.searchsorted(cumulative, b - 1e-12) + 1) for b in bands] + [len(shares)]
    edges, start = [], 0
    for end in ends:
        end = min(max(end, start), len(shares))
        if end > start:
            edges.append((start, end))
        start = end
    return edges


def directions_summary(data: np.ndarray, samples: np.ndarray, bands: tuple[float, ...] = BANDS,
                       placement: np.ndarray | None = None) -> dict:
    """How ``samples`` fill the principal directions of ``data``, both (N windows, K tokens, D),
    window i of each from the same test window; ``placement`` (N, K, 2), the pelvis's floor
    position per token, adds each direction's R² of it, the "placement" row and the "steps" row
    (the plane that carries each token's floor step, ``step_plane``). See the module
    docstring. Raises ValueError for shapes that do not pair up or windows of fewer than 2
    tokens."""
    data, samples = np.asarray(data, np.float64), np.asarray(samples, np.float64)
    if data.ndim != 3 or data.shape != samples.shape:
        raise ValueError(f"latent directions: data {data.shape} and samples {samples.shape} must be "
                         "the same (windows, tokens, channels)")
    if data.shape[1] < 2 or data.shape[0] < 2:
        raise ValueError(f"latent directions: needs at least 2 windows of 2 tokens, got {data.shape}")
    mean, values, directions = principal_axes(data)
    p_data, p_samples = (data - mean) @ directions, (samples - mean) @ directions  # (N, K, D)
    moments = {"data": window_moments(p_data), "samples": window_moments(p_samples)}
    energy = {k: m[0] for k, m in moments.items()}
    step = {k: m[1] for k, m in moments.items()}
    data_energy = energy["data"].mean(0)
    if not data_energy.sum() > 0:
        raise ValueError("latent directions: the encoder's latents do not vary over these windows")
    shares = data_energy / data_energy.sum()
    with np.errstate(divide="ignore", invalid="ignore"):  # a direction the data never moves along
        per_direction = {
            "share": shares.tolist(),
            "spread": _finite(energy["samples"].mean(0) / data_energy),
            "data_change": _finite(step["data"].mean(0) / (2 * data_energy)),
            "sample_change": _finite(step["samples"].mean(0) / (2 * data_energy)),
        }

    def row(chosen) -> dict:
        return subspace_row(energy["data"][:, chosen].sum(1), energy["samples"][:, chosen].sum(1),
                            step["data"][:, chosen].sum(1), step["samples"][:, chosen].sum(1),
                            float(shares[chosen].sum()))

    summary = {"windows": int(data.shape[0]), "tokens": int(data.shape[1]),
               "channels": int(data.shape[2]),
               "participation": {"data": participation(values),
                                 "samples": participation(principal_axes(samples)[1])},
               "bands": [{"directions": [start, end], **row(slice(start, end))}
                         for start, end in band_edges(shares, bands)],
               "per_direction": per_direction}
    if placement is not None:
        placement = np.asarray(placement, np.float64)
        r2 = placement_r2(p_data, placement)
        per_direction["placement_r2"] = r2.tolist()
        carriers = np.flatnonzero(r2 >= PLACEMENT_R2)
        if len(carriers):
            summary["placement"] = {"directions": carriers.tolist(), **row(carriers)}
        plane, fit = step_plane(p_data, placement)
        if plane is not None:
            data_on, step_on = (m.sum(1) for m in window_moments(p_data @ plane))
            samples_on, samples_step_on = (m.sum(1) for m in window_moments(p_samples @ plane))
            summary["steps"] = {"r2": fit, **subspace_row(
                data_on, samples_on, step_on, samples_step_on,
                float(data_on.mean() / data_energy.sum()))}
    return summary


def window_moments(projections: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, K, D) projections -> per window and direction (N, D): the mean p² and the mean
    squared token-to-token step."""
    return (projections ** 2).mean(1), (np.diff(projections, axis=1) ** 2).mean(1)


def subspace_row(data_energy: np.ndarray, sample_energy: np.ndarray, data_step: np.ndarray,
                 sample_step: np.ndarray, share: float) -> dict:
    """A table row from per-window figures along some directions: mean p² and mean squared
    token step, the data's and the samples' (each (N,)), and the directions' share of the data's
    variance; the ratios with their paired 95 % intervals over windows."""
    a, b, c, d = data_energy, sample_energy, data_step, sample_step
    figures = {"spread": paired_comparison(b, a), "data_change": paired_comparison(c / 2, a),
               "change_ratio": paired_comparison(d, c)}
    return {"share": share, **{f"{name}{k[5:]}": v for name, out in figures.items()
                               for k, v in out.items() if k.startswith("ratio")}}


def _finite(values: np.ndarray) -> list[float | None]:
    """A list for JSON: None where a ratio has no value (its data side is 0)."""
    return [float(v) if np.isfinite(v) else None for v in values]


def placement_r2(projections: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """(N, K, D) projections and (N, K, 2) floor positions -> (D,) the share of the positions'
    variance about their mean that a line fit on each direction alone explains."""
    if placement.shape != projections.shape[:2] + (2,):
        raise ValueError(f"latent directions: placement {placement.shape} must be (windows, "
                         f"tokens, 2) for latents {projections.shape}")
    x = projections.reshape(-1, projections.shape[-1])
    y = placement.reshape(-1, 2)
    x, y = x - x.mean(0), y - y.mean(0)
    total = (y ** 2).sum()
    if total == 0:
        return np.zeros(x.shape[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        explained = ((x.T @ y) ** 2).sum(1) / (x ** 2).sum(0)  # per direction, both coordinates
    return np.nan_to_num(explained / total)


def step_plane(projections: np.ndarray, placement: np.ndarray) -> tuple[np.ndarray | None, float]:
    """(N, K, D) projections and (N, K, 2) floor positions -> the (D, 2) orthonormal directions
    of a ridge fit (``STEP_RIDGE``) of each token's floor step on its projections, and the fit's
    R²; (None, 0.0) where the floor never moves."""
    x = projections[:, 1:].reshape(-1, projections.shape[-1])
    y = np.diff(placement, axis=1).reshape(-1, 2)
    x, y = x - x.mean(0), y - y.mean(0)
    total = float((y ** 2).sum())
    if not total > 0:
        return None, 0.0
    gram = x.T @ x
    ridge = STEP_RIDGE * np.trace(gram) / gram.shape[0]
    weights = np.linalg.solve(gram + ridge * np.eye(gram.shape[0]), x.T @ y)
    fit = 1.0 - float(((y - x @ weights) ** 2).sum()) / total
    plane, _ = np.linalg.qr(weights)
    return plane, fit


def pelvis_floor(layout, stride: int) -> Callable[[dict], np.ndarray]:
    """A window item -> its pelvis's floor position (x, z; y is up) per latent token of ``stride``
    frames, the mean over the token's frames: what ``LatentRecorder.place`` takes."""
    def place(item: dict) -> np.ndarray:
        icosahedra, _ = layout.split(np.asarray(item["motion"], np.float64))
        pelvis = icosahedra[:, layout.joint(ROOT)].mean(-2)[:, [0, 2]]
        return pelvis.reshape(-1, stride, 2).mean(1)

    return place


@dataclass
class LatentRecorder:
    """The flow's sample latents and the encoder's latents of the same windows, gathered as a
    model row's windows are generated (``observe``)."""

    encode: Callable[[dict], np.ndarray]  # window item -> its (K, Dz) standardized encoder means
    # window item -> the pelvis's floor position (K, 2) per token; None: no placement row
    place: Callable[[dict], np.ndarray] | None = None
    data: list[np.ndarray] = field(default_factory=list)
    samples: list[np.ndarray] = field(default_factory=list)
    placement: list[np.ndarray] = field(default_factory=list)

    def observe(self, run: Callable) -> Callable:
        """Wrap a ``run(item, index) -> generation Result`` into a ``produce(item, index) ->
        motion`` that keeps the result's latents and the item's encoder latents on the way."""
        def produce(item: dict, index: int):
            result = run(item, index)
            if result.latents is None:
                raise ValueError("latent directions: the generator kept no latents")
            self.samples.append(np.asarray(result.latents, np.float32))
            self.data.append(np.asarray(self.encode(item), np.float32))
            if self.place is not None:
                self.placement.append(np.asarray(self.place(item), np.float32))
            return result.motion

        return produce

    def summary(self) -> dict | None:
        """``directions_summary`` of what was observed; None before two windows."""
        if len(self.data) < 2:
            return None
        return directions_summary(np.stack(self.data), np.stack(self.samples),
                                  placement=np.stack(self.placement) if self.placement else None)


def _cell(row: dict, key: str, digits: int = 2) -> str:
    return with_interval(row.get(key), row.get(f"{key}_low"), row.get(f"{key}_high"), digits)


def directions_markdown(summary: dict, caption: str) -> str:
    """A ``directions_summary`` as a markdown table of its bands under ``caption``."""
    lines = [caption, "",
             f"Directions effectively filled (participation ratio of {summary['channels']}): data "
             f"{summary['participation']['data']:.1f}, samples "
             f"{summary['participation']['samples']:.1f}.", "",
             "| directions | share of the data's variance | samples' spread ÷ data's | data's "
             "token-to-token change | samples' change ÷ data's |", "|---|---|---|---|---|"]

    def line(name: str, row: dict) -> str:
        return (f"| {name} | {row['share']:.3f} | {_cell(row, 'spread')} | "
                f"{_cell(row, 'data_change', 3)} | {_cell(row, 'change_ratio')} |")

    lines += [line(f"{row['directions'][0] + 1}-{row['directions'][1]}", row)
              for row in summary["bands"]]
    notes = []
    if "steps" in summary:
        lines.append(line("steps (a plane)", summary["steps"]))
        notes += ["", f"Steps: the plane of a ridge fit of each token's pelvis floor step on its "
                  f"latents, which explains {summary['steps']['r2']:.2f} of the data's steps."]
    if "placement" in summary:
        chosen = summary["placement"]["directions"]
        r2 = summary["per_direction"]["placement_r2"]
        lines.append(line("placement: " + ", ".join(str(k + 1) for k in chosen),
                          summary["placement"]))
        notes = ["", "Placement: the directions each of which alone explains at least "
                 f"{PLACEMENT_R2:.0%} of the pelvis's floor position (R²: "
                 + ", ".join(f"{k + 1}: {r2[k]:.2f}" for k in chosen) + ")."] + notes
    return "\n".join(lines + notes) + "\n"


def plot_directions(path: Path, summary: dict) -> Path:
    """Per direction: the data's variance share (log), and the samples' spread and change
    against the data's (log; 1 = as the data)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..generation.plots import save_figure

    per = summary["per_direction"]
    k = np.arange(1, len(per["share"]) + 1)
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.0, 3.6))
    left.semilogy(k, per["share"], "k.-", lw=1)
    if "placement" in summary:
        carriers = np.array(summary["placement"]["directions"])
        left.semilogy(carriers + 1, np.array(per["share"])[carriers], "o", mfc="none",
                      color="tab:green", label="carries the pelvis's floor position")
        left.legend(fontsize=7)
    left.set_xlabel("principal direction of the data's latents")
    left.set_ylabel("share of the data's variance")
    left.set_title("Where the data's latents vary")
    spread = np.array(per["spread"], dtype=float)  # None (no data along it) -> NaN, not drawn
    right.semilogy(k, spread, ".-", color="tab:red", lw=1, label="samples' spread ÷ data's")
    change = np.array(per["sample_change"], dtype=float) / np.array(per["data_change"], dtype=float)
    right.semilogy(k, change, ".-", color="tab:blue", lw=1, label="samples' change ÷ data's")
    right.axhline(1.0, color="k", ls="--", lw=0.8)
    for row in summary["bands"][:-1]:
        for axis in (left, right):
            axis.axvline(row["directions"][1] + 0.5, color="0.7", lw=0.8)
    right.set_xlabel("principal direction of the data's latents")
    right.set_title("The flow's samples against the data")
    right.legend(fontsize=7)
    for axis in (left, right):
        axis.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)
