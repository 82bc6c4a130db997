"""Record what the decoding chain reads, then replay the chain with other decoding settings.

sarah-eval's offline model row and its VAE row decode latent tokens into frames and send them
through the decoding chain (seams, root hold, rigid skeleton, foot lock: ``sampling.decoding``).
This script records those frames and their decoded stance on a split's windows once, checks
that the chain gives the model row back to the bit, and scores the chain's output with the
model's own decoding settings and with each ``--try`` (decoding settings only, as ``sarah-train
--stage model --set`` takes them; several joined by commas): FGD_acc per batch of 16 and pooled
(the whole shell, the legs, the feet; ×10^5 (cm/s²)², as sarah-eval's), the feet's steps a
window (``metrics.foot_steps``), the share of them lasting the fixtures' 5 frames, the
stance head's lifts a window, and, from recordings that hold the users' floor paths (since the
seventy-seventh run), Head Ang. beside the data's and the look-away share: a decoding that holds
or turns the body moves where it looks. A decoding setting is read in seconds, not a new
evaluation (docs/results.md, seventy-fifth run). ``--anatomy`` adds a table of each body part's
acceleration by time scale and by place in a latent block: its energy below and above
``BAND_HZ`` against the data's, and its seam share (docs/results.md, seventy-eighth run), and a
table of each body part's FGD_acc beside the real floor's, the recording's first half of windows
against its second: where a decoding's distance lies (seventy-ninth run). ``--stages`` adds
the shell's FGD_acc and the anatomy's figures after each filter of the chain in turn, the
decoder's own frames first: what each filter adds to and takes from each part, and
``--stages-plot`` draws it (eightieth run). ``--legs`` splits the legs' FGD_acc by the leg joints
their points lie nearest to (the hips, by axis too, and each knee and ankle), with what lies
between the two legs (both together less each alone) beside the real floor's, and correlates the
left and right knees' and ankles' accelerations: the data's legs move together, the lock's each
on its own (eighty-first run). ``--covariance`` splits each part's FGD_acc into what the
accelerations' spread accounts for and what the directions of their principal axes add
(``metrics.frechet_terms``): the model's excess over the real floor is in the directions far
more than in the energy (eighty-third run). ``--gait`` says how the body walks: the pelvis's
moves on the floor (how many a window, how long, how far, how fast), the frames in which both
feet step, and where the pelvis's acceleration falls against the feet's steps: the data's
people stand still and step in moves of a fraction of a second, the model's pelvis creeps, and
``--gait-plot`` draws the pelvis's speed frame by frame in three windows (eighty-fourth run).
``--feet`` says how far apart the feet stand: how often the ankles come within ``NEAR`` of each
other, their gap along the hips' line (below the foot lock's ``vae.foot_gap``, below 0: crossed)
and its percentiles; the data's never cross, a lock that holds a foot while the body turns over
it lets them, and ``--feet-plot`` draws that gap frame by frame in the three windows where the
decodings' feet come nearest (hundred-and-third run); and how far each ankle stands from under
its hip, where the data's stand and a held foot is left behind, and how far the knees bend,
which ``--knees-plot`` draws frame by frame in three windows (hundred-and-fourth run):

    python scripts/decode_replay.py --run MODEL --shards test_shards --split train --windows 96 \\
        --noise-scale 0.3 --cfg 4.5 --guide user_head --guidance-interval 0,0.75 \\
        --imputation trajectory --record decodes.npz --try vae.root_hold=0.15
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --try vae.foot_lock=0.2
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --anatomy
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --stages-plot stages.png
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --legs
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --covariance
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --gait-plot gait.png
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --feet --try vae.foot_gap=0
    python scripts/decode_replay.py --run MODEL --replay decodes.npz --feet-plot feet.png --try vae.foot_gap=0
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from sarah_cli.arguments import add_sampling_arguments, sampling_of
from sarah_data.atomic import atomic_path
from sarah_data.bone_turns import unit
from sarah_data.constants import FPS
from sarah_data.skeleton import FEET, ROOT, MotionLayout, shell_parts
from sarah_models.config import HISTORY_WINDOW, RunConfig
from sarah_models.training import model_file
from sarah_models.evaluation.metrics import foot_steps
from sarah_models.evaluation.metrics.head_angle import head_angle
from sarah_models.evaluation.metrics.look_away import looks_away
from sarah_models.evaluation.metrics.clips import accelerations, step_lengths
from sarah_models.evaluation.metrics.fgd_acc import METRIC as FGD_ACC
from sarah_models.evaluation.metrics.frechet import FrechetTerms, frechet_distance, frechet_terms
from sarah_models.evaluation.metrics.spec import MetricsConfig
from sarah_models.evaluation.metrics.seam_share import points_seam_share
from sarah_models.evaluation.metrics.table import bootstrap_interval, paired_comparison
from sarah_models.evaluation.runner import EvalConfig
from sarah_models.sampling.decoding import reads_stance, stream_decoding
# how long the fixtures' feet travel in a step, which the foot lock's data steps copy
from sarah_models.sampling.foot_lock import GAP, STANCE_SWING_FRAMES, hips_line

BATCH = 16  # clips per batch of the per-batch column, as sarah-eval's default
# The anatomy's time scales: the accelerations of the motion averaged over BAND_FRAMES frames (a
# moving average, which passes gestures and steps and has its first zero at fps / BAND_FRAMES =
# BAND_HZ), and what is left above them.
BAND_FRAMES = 5
BAND_HZ = FPS / BAND_FRAMES
PARTS = ("legs", "feet")
ROWS = ("model", "vae")


def record(models, shards: Path, split: str, windows: int, sampling: EvalConfig,
           window: int = 400) -> dict[str, np.ndarray]:
    """The ground truth of ``windows`` evenly spaced windows of ``split`` and, for the model's
    offline row and the VAE row, the decoder's frames and stance as the chain reads them. The
    model's frames decode ``window_generator``'s latents; SystemExit unless the chain gives its
    motion back to the bit."""
    import torch

    from sarah_data.dataset import WindowDataset
    from sarah_models.evaluation.runner import window_generator, window_seed
    from sarah_models.evaluation.windows import TestWindows, select_windows
    from sarah_models.sampling.decoding import decoder_frames
    from sarah_models.sampling.stream import window_history

    if models.flow.config.user_relative:
        sys.exit("decode_replay: this flow's offline solve decodes block by block "
                 "(flow.user_relative); only flows that decode a window at once are recorded")
    dataset = WindowDataset.sliding(shards, split, extractor=models.features, window=window)
    chosen = TestWindows(dataset, select_windows(len(dataset), windows))
    if not len(chosen):
        sys.exit(f"decode_replay: {shards}: split {split!r} has no {window}-frame windows")
    if sampling.history_tokens == HISTORY_WINDOW:  # as sarah-eval resolves it
        sampling = replace(sampling, history_tokens=window_history(models.flow))
    generate = window_generator(models, replace(sampling, protocol="offline"), None)
    vae, nz = models.vae, models.normalizer
    out: dict[str, list] = {"gt": [], "user": [],
                            **{f"{r}_{k}": [] for r in ROWS for k in ("frames", "stance")}}
    with torch.inference_mode():
        for i in range(len(chosen)):
            item = chosen[i]
            result = generate(item, i)
            tokens = nz.denormalize("latent", torch.as_tensor(result.latents))[None]
            frames, stance = decoder_frames(vae, nz, tokens, window_seed(sampling.seed, i))
            user = item["user_head"].double().numpy()  # the window frame, as the chain's
            if not np.array_equal(stream_decoding(vae, nz)(frames, stance, user).astype(np.float32),
                                  result.motion):
                sys.exit(f"decode_replay: window {i}: the chain does not give the model row back "
                         f"from its recorded frames")
            means, _ = vae.encode(nz.normalize("motion", item["motion"])[None])
            rows = {"model": (frames, stance), "vae": decoder_frames(vae, nz, means, i)}
            for row, (f, s) in rows.items():
                out[f"{row}_frames"].append(f.astype(np.float32))
                out[f"{row}_stance"].append(np.ones(f.shape[:1] + (len(FEET),), bool)
                                            if s is None else s)
            out["gt"].append(item["motion"].numpy())
            out["user"].append(user)
    return {key: np.stack(value) for key, value in out.items()}


def tried_models(models, source: Path, settings: list[str]):
    """``models`` decoding with ``settings`` set: written as a model file, as ``sarah-train
    --stage model --set`` writes one, and loaded back."""
    if not settings:
        return models
    with tempfile.TemporaryDirectory() as folder:
        path = model_file.write_model_file(source, Path(folder) / "tried.safetensors", settings)
        return model_file.load_model_file(path, device="cpu")


def chain_users(models, users: np.ndarray | None, windows: int) -> list:
    """The users' floor paths each window's chain reads: ``users``, or Nones where the recording
    has none (recordings before the seventy-seventh run), SystemExit where the chain needs them."""
    if users is not None:
        return list(users)
    if stream_decoding(models.vae, models.normalizer).reads_user:
        sys.exit("decode_replay: this decoding turns the held body toward the user "
                 "(vae.root_hold_turn) and the recording has no user paths: record it again")
    return [None] * windows


def decode(models, frames: np.ndarray, stance: np.ndarray, users: np.ndarray | None) -> np.ndarray:
    """Every window's recorded frames through a new chain of ``models``' decoding; ``users``
    (windows, T, 2) the user's floor paths, which a root hold that turns reads."""
    steps = reads_stance(models.vae)
    return np.stack([stream_decoding(models.vae, models.normalizer)(
        f.astype(np.float64), s if steps else None, u).astype(np.float32)
        for f, s, u in zip(frames, stance, chain_users(models, users, len(frames)))])


def stages(models, frames: np.ndarray, stance: np.ndarray, users: np.ndarray | None):
    """The recorded frames, then every window's motion after each filter of ``models``' decoding
    chain in turn: (the filter's name, (windows, T, D) float32) pairs, ``"decoder"`` first; the
    last is ``decode``'s. Each window's chain is fed its frames as ``decode`` feeds them, one
    filter at a time."""
    steps = reads_stance(models.vae)
    chains = [stream_decoding(models.vae, models.normalizer) for _ in frames]
    users = chain_users(models, users, len(frames))
    motion = [f.astype(np.float64) for f in frames]
    yield "decoder", np.stack(motion).astype(np.float32)
    for k, name in enumerate(type(f).__name__ for f in chains[0].filters):
        motion = [chain.filters[k](m, s if steps else None, u)
                  for chain, m, s, u in zip(chains, motion, stance, users)]
        yield name, np.stack(motion).astype(np.float32)


def shell_accelerations(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """(clips, frames, D) motion -> (clips, frames - 2, points, 3) shell accelerations, m/s²."""
    return np.stack([accelerations(layout.split(x)[1]) for x in motion])


# FGD_acc of accelerations in m/s² as sarah-eval shows it: in its report unit, ÷ its display scale
SCALE = (1.0 / MetricsConfig().report_unit) ** FGD_ACC.length_power / FGD_ACC.scale


def features(acc: np.ndarray, points, clips=slice(None), axes=(0, 1, 2)) -> np.ndarray:
    """(clips, frames, points, 3) accelerations -> (samples, len(axes) * len(points)): FGD_acc's
    samples, one a frame, of ``points`` (of their ``axes`` alone: 1 is the vertical)."""
    return acc[clips][:, :, points][..., list(axes)].reshape(-1, len(axes) * len(points))


def batches(acc: np.ndarray, real: np.ndarray, points, axes=(0, 1, 2)):
    """FGD_acc's samples of ``points`` (of their ``axes``) batch by batch of ``BATCH`` clips:
    (generated, real) pairs, clip i against real clip i."""
    for s in range(0, len(acc), BATCH):
        yield (features(acc, points, slice(s, s + BATCH), axes),
               features(real, points, slice(s, s + BATCH), axes))


def batch_distances(acc: np.ndarray, real: np.ndarray, points, axes=(0, 1, 2)) -> list[float]:
    """FGD_acc of ``points`` per batch of ``BATCH`` clips (clip i against real clip i), ×10^5;
    of their ``axes`` alone where given."""
    return [frechet_distance(a, b) * SCALE for a, b in batches(acc, real, points, axes)]


def distances(acc: np.ndarray, real: np.ndarray, parts: dict,
              batches: dict[str, np.ndarray] | None = None) -> dict[str, float]:
    """FGD_acc per batch of ``BATCH`` clips and pooled, of the shell and of ``PARTS``, ×10^5
    (cm/s²)², with the shell's 95 % bootstrap interval over batches; NaN for a part no shell
    point lies nearest to. ``batches``: ``part_distances`` of the same accelerations, when
    computed already (the parts' table)."""
    out = {f"{part} {kind}": float("nan") for part in PARTS for kind in ("batch", "pooled")}
    shown = {p: parts[p] for p in PARTS if p in parts}
    if batches is None:
        batches = part_distances(acc, real, shown)
    for part, points in (("shell", np.arange(acc.shape[2])), *((p, list(q)) for p, q in shown.items())):
        out[f"{part} batch"] = float(np.mean(batches[part]))
        out[f"{part} pooled"] = frechet_distance(features(acc, points), features(real, points)) * SCALE
        if part == "shell":  # sarah-eval's interval: the batches' mean, bootstrapped
            out["shell interval"] = bootstrap_interval(batches[part])
    return out


def part_distances(acc: np.ndarray, real: np.ndarray, parts: dict) -> dict[str, np.ndarray]:
    """FGD_acc per batch of ``BATCH`` clips of the whole shell and of every body part, each
    part's batches as an array (its mean is the figure, its batches the interval's samples)."""
    return {part: np.asarray(batch_distances(acc, real, list(points)))
            for part, points in (("shell", range(acc.shape[2])), *parts.items())}


def real_halves(real: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The data's first half of windows and its second, whose distance is the real floor: what
    two sets of real windows score, the floor no decoding gets under at this batch size; None
    with fewer than two batches' windows."""
    half = len(real) // 2
    return None if half < BATCH else (real[:half], real[half:2 * half])


def real_floor(real: np.ndarray, parts: dict) -> dict[str, np.ndarray] | None:
    """``part_distances`` of the data's ``real_halves``; None without them."""
    halves = real_halves(real)
    return None if halves is None else part_distances(*halves, parts)


def covariance_terms(acc: np.ndarray, real: np.ndarray, parts: dict) -> dict[str, FrechetTerms]:
    """FGD_acc of the whole shell and of every body part split into ``frechet_terms``' three
    terms per batch of ``BATCH`` clips (clip i against real clip i): each term's mean over the
    batches, ×10^5 (cm/s²)² as the distance (energy: the batches' mean ratio)."""
    out = {}
    for part, points in (("shell", range(acc.shape[2])), *parts.items()):
        terms = [frechet_terms(a, b) for a, b in batches(acc, real, list(points))]
        out[part] = FrechetTerms(**{
            f.name: float(np.mean([getattr(t, f.name) for t in terms]))
            * (1.0 if f.name == "energy" else SCALE) for f in fields(FrechetTerms)})
    return out


def covariance_row(label: str, decoding: str, found: dict[str, FrechetTerms]) -> str:
    """Each part's FGD_acc as spectrum + orientation (+ mean, where it reaches 0.05), and its
    acceleration energy ÷ the data's."""
    cells = []
    for terms in found.values():
        mean = f" + {terms.mean:.1f}" if terms.mean >= 0.05 else ""
        cells.append(f"{terms.total:.1f} = {terms.spectrum:.1f} + {terms.orientation:.1f}{mean}, "
                     f"{terms.energy:.2f}x")
    return f"| {label} | {decoding} | " + " | ".join(cells) + " |"


def parts_row(label: str, decoding: str, found: dict, floor: dict | None) -> str:
    """Each part's FGD_acc with its 95 % bootstrap interval over batches and, given the real
    floor, the figure ÷ the floor's."""
    cells = []
    for part, batches in found.items():
        cell = "{:.1f} ({:.1f}-{:.1f})".format(batches.mean(), *bootstrap_interval(batches))
        if floor is not None and found is not floor:
            cell += f", {batches.mean() / floor[part].mean():.1f}x"
        cells.append(cell)
    return f"| {label} | {decoding} | " + " | ".join(cells) + " |"


def anatomy(motion: np.ndarray, acc: np.ndarray, layout: MotionLayout, parts: dict, stride: int
            ) -> dict[str, np.ndarray]:
    """Each body part's shell points, window by window (windows, 3): their seam share
    (``metrics.seam_share``'s, the part's points together) and their acceleration energy (mean
    squared, (m/s²)²) below and above ``BAND_HZ``, on the frames whose average lies inside the
    window; ``acc`` is ``shell_accelerations(motion, layout)``, which the FGD_acc columns have
    computed already."""
    from scipy.ndimage import uniform_filter1d

    inside = slice(BAND_FRAMES // 2, -(BAND_FRAMES // 2))
    acc = acc[:, inside]
    slow = shell_accelerations(uniform_filter1d(motion.astype(np.float64), BAND_FRAMES, axis=1),
                               layout)[:, inside]
    out = {}
    for part, points in parts.items():
        points = list(points)
        seams = [points_seam_share(layout.split(x)[1][:, points], stride) for x in motion]
        low = slow[:, :, points]
        out[part] = np.stack([seams, np.mean(np.sum(low ** 2, axis=-1), axis=(1, 2)),
                              np.mean(np.sum((acc[:, :, points] - low) ** 2, axis=-1), axis=(1, 2))],
                             axis=1)
    return out


def energy_ratios(windows: np.ndarray, truth: np.ndarray) -> list[dict[str, float]]:
    """A part's ``anatomy`` (windows, 3) against the data's on the same windows: its energy below
    and above ``BAND_HZ`` ÷ the data's, each ``paired_comparison``'s dict."""
    return [paired_comparison(windows[:, k], truth[:, k]) for k in (1, 2)]


def anatomy_cells(found: dict, truth: dict) -> list[str]:
    """Seam share / energy below / above BAND_HZ of each part, the windows' means with 95 %
    bootstrap intervals over windows; the energies ÷ the data's on the same windows, paired
    (``truth``'s own cells, ``found is truth``: their RMS in cm/s²)."""
    cells = []
    for part, windows in found.items():
        seams, low, high = windows.mean(axis=0)
        seam = "{:.2f} ({:.2f}-{:.2f})".format(seams, *bootstrap_interval(windows[:, 0]))
        if found is truth:
            cells.append(f"{seam} / {100 * low ** 0.5:.0f} / {100 * high ** 0.5:.0f} cm/s²")
            continue
        ratios = energy_ratios(windows, truth[part])
        cells.append(seam + "".join(" / {ratio:.2f}x ({ratio_low:.2f}-{ratio_high:.2f})".format(**r)
                                    for r in ratios))
    return cells


def anatomy_row(label: str, decoding: str, found: dict, truth: dict) -> str:
    """``anatomy_cells`` as a row of the anatomy's table."""
    return f"| {label} | {decoding} | " + " | ".join(anatomy_cells(found, truth)) + " |"


def stage_row(label: str, decoding: str, stage: str, shell: np.ndarray, found: dict,
              truth: dict) -> str:
    """A row of the stages' table: the shell's FGD_acc per batch after ``stage`` (95 % bootstrap
    over batches) and ``anatomy_cells``."""
    fgd = "{:.1f} ({:.1f}-{:.1f})".format(shell.mean(), *bootstrap_interval(shell))
    return (f"| {label} | {decoding} | {stage} | {fgd} | "
            + " | ".join(anatomy_cells(found, truth)) + " |")


def stage_series(by_stage: list, truth: dict) -> dict[tuple[str, str], dict]:
    """The stages' table as numbers, per (motion, decoding) in the table's order: ``stages`` (the
    names), ``fgd`` (stages, 3: the shell's FGD_acc per batch, its 95 % interval's ends) and
    ``parts``: each body part's (stages, 2, 3) energy below and above ``BAND_HZ`` ÷ the data's, each
    with its paired 95 % interval's ends (NaN where the data's energy is 0). ``by_stage`` holds
    (motion, decoding, stage, shell batches, ``anatomy``) tuples."""
    out: dict[tuple[str, str], dict] = {}
    for label, decoding, stage, shell, found in by_stage:
        group = out.setdefault((label, decoding), {"stages": [], "fgd": [],
                                                    "parts": {part: [] for part in found}})
        group["stages"].append(stage)
        group["fgd"].append((float(np.mean(shell)), *bootstrap_interval(shell)))
        for part, windows in found.items():
            ratios = energy_ratios(windows, truth[part])
            group["parts"][part].append([[r.get(key, np.nan) for key in ("ratio", "ratio_low", "ratio_high")]
                                         for r in ratios])
    for group in out.values():
        group["fgd"] = np.asarray(group["fgd"], dtype=np.float64)
        group["parts"] = {part: np.asarray(v, dtype=np.float64) for part, v in group["parts"].items()}
    return out


def plot_stages(path: Path, series: dict[tuple[str, str], dict]) -> Path:
    """``stage_series`` drawn: a column per motion and decoding, the shell's FGD_acc on top and
    each part's energy below and above ``BAND_HZ`` ÷ the data's under it (log scales, 95 %
    intervals as bars, the data's energy as a dashed line at 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sarah_models.generation.plots import save_figure

    def bars(ax, x, values, **style):  # values (stages, 3): figure, interval's low and high ends
        ax.errorbar(x, values[:, 0], yerr=np.abs(values[:, 1:].T - values[:, 0]), marker="o",
                    capsize=2, **style)

    fig, axes = plt.subplots(3, len(series), figsize=(4.5 * len(series), 9.5), squeeze=False,
                             sharey="row")
    for column, ((label, decoding), group) in enumerate(series.items()):
        x = np.arange(len(group["stages"]))
        bars(axes[0, column], x, group["fgd"], color="black")
        axes[0, column].set_title(f"{label}, {decoding}", fontsize=9)
        for band in (0, 1):
            ax = axes[band + 1, column]
            for part, values in group["parts"].items():
                bars(ax, x, values[:, band], label=part)
            ax.axhline(1.0, color="grey", linestyle="--", linewidth=1)
        for ax in axes[:, column]:
            ax.set_yscale("log", nonpositive="mask")
            ax.set_xticks(x, group["stages"], rotation=30, ha="right", fontsize=8)
    axes[0, 0].set_ylabel(f"FGD_acc of the shell, per batch of {BATCH}")
    axes[1, 0].set_ylabel(f"energy below {BAND_HZ:g} Hz ÷ the data's")
    axes[2, 0].set_ylabel(f"energy above {BAND_HZ:g} Hz ÷ the data's")
    axes[1, -1].legend(fontsize=7, loc="best")
    fig.suptitle("The decoding chain, stage by stage: the decoder's frames, then after each filter",
                 fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


# The legs' table: the legs' shell points by the leg joints each lies nearest to, a group per
# entry; "between the two" is what the two legs' points score together beyond each leg alone.
LEG_GROUPS = {"hips": ("left_hip", "right_hip"), "left knee and ankle": ("left_knee", "left_ankle"),
              "right knee and ankle": ("right_knee", "right_ankle")}
LEG_COLUMNS = ("hips", "hips horizontal", "hips vertical", "left knee and ankle",
               "right knee and ankle", "both knees and ankles", "between the two")
# the left and right joints' accelerations the table correlates: the data's knees move together
# on the floor, their ankles vertically (docs/results.md, seventy-eighth run)
LEG_PAIRS = (("knee", 0), ("knee", 2), ("ankle", 1))


def leg_groups(icosahedra: np.ndarray, shell: np.ndarray, layout: MotionLayout) -> dict[str, list[int]]:
    """One frame's icosahedra and shell -> the legs' shell points by the ``LEG_GROUPS`` entry
    whose joint each lies nearest to (``shell_parts``' "legs", split); every entry, empty where
    no point lies nearest to its joints."""
    found = shell_parts(icosahedra, shell, layout.joint_names, LEG_GROUPS)
    return {group: list(found.get(group, ())) for group in LEG_GROUPS}


def leg_distances(acc: np.ndarray, real: np.ndarray, groups: dict[str, list[int]]
                  ) -> dict[str, np.ndarray]:
    """FGD_acc per batch of ``BATCH`` clips of each of ``LEG_COLUMNS``: the hips' points (all
    three axes, the floor's two, the vertical), each leg's knee and ankle points, both legs'
    together, and both less each alone, batch by batch; NaN where a group has no points."""
    hips, left, right = (groups[g] for g in LEG_GROUPS)
    out = {column: np.asarray(batch_distances(acc, real, points, axes) if points else [np.nan])
           for column, points, axes in (
        ("hips", hips, (0, 1, 2)), ("hips horizontal", hips, (0, 2)), ("hips vertical", hips, (1,)),
        ("left knee and ankle", left, (0, 1, 2)), ("right knee and ankle", right, (0, 1, 2)),
        ("both knees and ankles", left + right, (0, 1, 2)))}
    out["between the two"] = (out["both knees and ankles"] - out["left knee and ankle"]
                              - out["right knee and ankle"])
    return out


def leg_correlations(motion: np.ndarray, layout: MotionLayout) -> list[float]:
    """The correlation of the left and right joint's frame-to-frame accelerations along an axis,
    pooled over every window's frames, for each of ``LEG_PAIRS`` (NaN where either stands still)."""
    names = sorted({f"{side}_{joint}" for joint, _ in LEG_PAIRS for side in ("left", "right")})
    acc_all = np.stack([accelerations(layout.joint_positions(x.astype(np.float64), names))
                        for x in motion])  # (windows, T - 2, joints, 3)
    out = []
    for joint, axis in LEG_PAIRS:
        sides = [names.index(f"{side}_{joint}") for side in ("left", "right")]
        acc = acc_all[:, :, sides, axis].reshape(-1, 2)
        still = not np.all(acc.std(axis=0) > 0)
        out.append(np.nan if still else float(np.corrcoef(acc[:, 0], acc[:, 1])[0, 1]))
    return out


def legs_row(label: str, decoding: str, found: dict[str, np.ndarray] | None,
             correlations: list[float]) -> str:
    """A row of the legs' table: each column's FGD_acc with its 95 % bootstrap interval over
    batches ("-" where ``found`` is None, the data's row without a real floor, or where a group
    has no points), and the left / right correlations."""
    cells = (["-"] * len(LEG_COLUMNS) if found is None else
             ["{:.1f} ({:.1f}-{:.1f})".format(found[c].mean(), *bootstrap_interval(found[c]))
              if np.isfinite(found[c]).all() else "-" for c in LEG_COLUMNS])
    return (f"| {label} | {decoding} | " + " | ".join(cells) + " | "
            + " / ".join(f"{c:.2f}" if np.isfinite(c) else "-" for c in correlations) + " |")


# m/s on the floor: faster, the pelvis moves. The data's people stand still between steps (0)
# and step at about 1.5 m/s at a move's peak; the model's pelvis creeps at a few cm/s (eighty-fourth run).
PELVIS_MOVE_SPEED = 0.1
GAIT_COLUMNS = ("moves a window (95 %)", "frames a move", "metres a move", "peak m/s",
                "share of frames moving", "share of frames both feet step",
                "share of its floor acceleration where no foot steps")


def gait(motion: np.ndarray, layout: MotionLayout) -> dict[str, np.ndarray]:
    """How the body walks: the pelvis's moves on the floor (runs of frame steps in which it moves
    faster than ``PELVIS_MOVE_SPEED``: a window's count, each move's frames, metres and peak
    speed), the share of frames it moves, the share of frame steps in which both feet step
    (``foot_steps``, the steps column's), and the share of the pelvis's floor acceleration
    energy at frames where neither foot steps. Per window, except the moves' own figures; and
    ``paths``, every window's (T, 2) floor path of the pelvis (x, z), which --gait-plot draws."""
    out: dict[str, list] = {key: [] for key in ("moves", "frames", "metres", "peak", "moving",
                                                 "both", "still", "energy", "paths")}
    for x in motion:
        joints = layout.joint_positions(np.asarray(x, dtype=np.float64), [ROOT, *FEET])
        path = joints[:, 0, [0, 2]]
        speed = step_lengths(path) * FPS
        runs = foot_steps(joints[:, :1], min_speed=PELVIS_MOVE_SPEED)[0]
        out["paths"].append(path)
        out["moves"].append(len(runs))
        for start, end in runs:
            out["frames"].append(end - start)
            out["metres"].append(speed[start:end].sum() / FPS)
            out["peak"].append(speed[start:end].max())
        out["moving"].append(np.mean(speed > PELVIS_MOVE_SPEED))
        stepping = np.zeros((len(x) - 1, len(FEET)), dtype=bool)
        for foot, steps_of_foot in enumerate(foot_steps(joints[:, 1:])):
            for start, end in steps_of_foot:
                stepping[start:end, foot] = True
        out["both"].append(np.mean(stepping.all(axis=1)))
        energy = (accelerations(path) ** 2).sum(axis=-1)  # at frames 1 .. T - 2
        still = ~(stepping[:-1].any(axis=1) | stepping[1:].any(axis=1))
        out["still"].append(energy[still].sum())
        out["energy"].append(energy.sum())
    return {key: np.asarray(value, dtype=np.float64) for key, value in out.items()}


def gait_row(label: str, decoding: str, found: dict[str, np.ndarray]) -> str:
    """A row of the gait table (``GAIT_COLUMNS``): the moves a window with their 95 % bootstrap
    interval over windows, each move's medians, and the windows' pooled shares."""
    moves = found["moves"]
    medians = [np.median(found[key]) if len(found[key]) else np.nan for key in ("frames", "metres", "peak")]
    still = found["still"].sum() / found["energy"].sum() if found["energy"].sum() > 0 else np.nan
    cells = ["{:.1f} ({:.1f}-{:.1f})".format(moves.mean(), *bootstrap_interval(moves)),
             *("-" if not np.isfinite(m) else f"{m:{f}}" for m, f in zip(medians, ("g", ".2f", ".2f"))),
             f"{found['moving'].mean():.2f}", f"{found['both'].mean():.3f}",
             "-" if not np.isfinite(still) else f"{still:.2f}"]
    return f"| {label} | {decoding} | " + " | ".join(cells) + " |"


GAIT_PLOT_WINDOWS = 3  # windows --gait-plot draws, evenly spaced: the first, the middle, the last


def evenly_spaced(windows: int, count: int = GAIT_PLOT_WINDOWS) -> list[int]:
    """``count`` of ``windows`` window indices, evenly spaced from the first to the last."""
    return sorted({int(w) for w in np.linspace(0, windows - 1, count).round()})


def plot_windows(path: Path, traces: list[tuple[str, str, np.ndarray]], windows: list[int],
                 first: int, unit: str, lines: list[tuple[float, str]], title: str) -> Path:
    """A figure of one panel per window (named by its index) with a line per motion and decoding
    (``traces``: label, decoding and (len(windows), n) values there, frame ``first`` on), the
    ground truth's first and black, and grey lines at (value, linestyle) ``lines``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sarah_models.generation.plots import save_figure

    fig, axes = plt.subplots(len(windows), 1, figsize=(11, 2.6 * len(windows)), squeeze=False,
                             sharex=True)
    for row, (ax, window) in enumerate(zip(axes[:, 0], windows)):
        for k, (label, decoding, values) in enumerate(traces):
            name = label if decoding in ("-", "the model's") else f"{label}, {decoding}"
            ax.plot((first + np.arange(values.shape[1])) / FPS, values[row], label=name,
                    linewidth=1.6 if k == 0 else 1.0, color="black" if k == 0 else None,
                    zorder=3 if k == 0 else 2)
        for value, style in lines:
            ax.axhline(value, color="grey", linestyle=style, linewidth=1)
        ax.set_ylabel(f"window {window}: {unit}")
    axes[-1, 0].set_xlabel("seconds")
    axes[0, 0].legend(fontsize=8, loc="upper right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_gait(path: Path, traces: list[tuple[str, str, np.ndarray]], windows: list[int]) -> Path:
    """The pelvis's speed on the floor, frame by frame, in ``windows`` (``plot_windows``;
    ``traces``: label, decoding and the pelvis's (len(windows), T, 2) floor paths there,
    ``gait``'s), the move speed dashed."""
    speeds = [(label, decoding, np.stack([step_lengths(path) * FPS for path in paths]))
              for label, decoding, paths in traces]
    return plot_windows(path, speeds, windows, 1, "m/s", [(PELVIS_MOVE_SPEED, "--")],
                        f"The pelvis's speed on the floor (dashed: {PELVIS_MOVE_SPEED:g} m/s, a move)")


NEAR = 0.1  # m: ankles nearer than this on the floor stand on each other's feet
FEET_COLUMNS = (f"ankles < {NEAR * 100:g} cm (95 %)", f"gap < {GAP * 100:g} cm (95 %)",
                "crossed (95 %)", "gap p1 / p5 / p50, cm", "ankle from under its hip, cm (95 %)",
                "from under its hip p90, cm", "knee angle, degrees (95 %)")


def feet_apart(motion: np.ndarray, layout: MotionLayout) -> dict[str, np.ndarray]:
    """How far apart the feet stand: per window, the shares of frames whose ankles come within
    ``NEAR`` on the floor, whose gap along the hips' line (the left ankle's offset from the right
    along the line from the right hip to the left) is below ``GAP``, the foot lock's default
    ``vae.foot_gap``, and below 0 (crossed); ``gap``, every frame's (metres); and ``under``, each
    ankle's distance on the floor from under its hip, every frame's (windows, T, 2; metres): the
    data's people stand on feet under their hips, a lock that holds a foot while the pelvis moves
    on leaves it behind; and ``knee``, each knee's angle between thigh and shin, every frame's
    (windows, T, 2; degrees, 180 straight): the data's people stand on straight legs, the
    decoder lower (hundred-and-fourth run)."""
    names = ("left_hip", "right_hip", "left_ankle", "right_ankle", "left_knee", "right_knee")
    joints = np.stack([layout.joint_positions(np.asarray(x, dtype=np.float64), list(names))
                       for x in motion])
    cosine = np.sum(unit(joints[:, :, :2] - joints[:, :, 4:]) * unit(joints[:, :, 2:4] - joints[:, :, 4:]),
                    axis=-1)  # thigh and shin, each from the knee
    joints = joints * np.array([1.0, 0.0, 1.0])
    across = hips_line(joints[:, :, 0], joints[:, :, 1])
    between = joints[:, :, 2] - joints[:, :, 3]
    gap = np.sum(between * across, axis=-1)
    return {"near": np.mean(np.linalg.norm(between, axis=-1) < NEAR, axis=1),
            "narrow": np.mean(gap < GAP, axis=1), "crossed": np.mean(gap < 0, axis=1), "gap": gap,
            "under": np.linalg.norm(joints[:, :, 2:4] - joints[:, :, :2], axis=-1),
            "knee": np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))}


def feet_row(label: str, decoding: str, found: dict[str, np.ndarray]) -> str:
    """A row of the feet table (``FEET_COLUMNS``): the shares in % of frames with their 95 %
    bootstrap interval over windows, the gap's percentiles over every frame, the windows' median
    distance of the ankles from under their hips (the mean over windows and its 95 % interval)
    and that distance's 90th percentile over every frame, and the windows' median knee angle
    (the mean over windows and its 95 % interval)."""
    cells = ["{:.2f} % ({:.2f}-{:.2f})".format(*(100 * np.array([found[key].mean(),
                                                                *bootstrap_interval(found[key])])))
             for key in ("near", "narrow", "crossed")]
    cells.append(" / ".join(f"{100 * q:.1f}" for q in np.percentile(found["gap"], [1, 5, 50])))
    cells.append(windows_median_cell(100 * found["under"]))
    cells.append(f"{100 * np.percentile(found['under'], 90):.1f}")
    cells.append(windows_median_cell(found["knee"]))
    return f"| {label} | {decoding} | " + " | ".join(cells) + " |"


def windows_median_cell(values: np.ndarray) -> str:
    """(windows, ...) values -> "mean (low-high)": each window's median, their mean over the
    windows and its 95 % bootstrap interval."""
    medians = np.median(values.reshape(len(values), -1), axis=1)
    return "{:.1f} ({:.1f}-{:.1f})".format(medians.mean(), *bootstrap_interval(medians))


FEET_PLOT_WINDOWS = 3  # windows --feet-plot draws: those where the decodings' feet come nearest


def nearest_windows(gaps: list[np.ndarray], count: int = FEET_PLOT_WINDOWS) -> list[int]:
    """The ``count`` windows whose feet come nearest (the lowest gap of any of ``gaps``, each a
    decoding's (windows, T) gaps), in window order."""
    lowest = np.min([gap.min(axis=1) for gap in gaps], axis=0)
    return sorted(int(w) for w in np.argsort(lowest, kind="stable")[:count])


def plot_feet(path: Path, traces: list[tuple[str, str, np.ndarray]], windows: list[int]) -> Path:
    """The feet's gap along the hips' line, frame by frame, in ``windows`` (``plot_windows``;
    ``traces``: label, decoding and the (len(windows), T) gaps there, ``feet_apart``'s), the foot
    lock's default gap dashed and 0 (crossed) dotted."""
    return plot_windows(path, [(label, decoding, 100 * gaps) for label, decoding, gaps in traces],
                        windows, 0, "cm", [(100 * GAP, "--"), (0.0, ":")],
                        f"The left ankle's gap from the right along the hips' line (dashed: "
                        f"{100 * GAP:g} cm, the foot lock's vae.foot_gap; dotted: crossed)")


def plot_knees(path: Path, traces: list[tuple[str, str, np.ndarray]], windows: list[int]) -> Path:
    """The knees' angle frame by frame (the two legs' mean, ``feet_apart``'s), in ``windows``
    (``plot_windows``; ``traces``: label, decoding and the (len(windows), T) angles there),
    straight dotted."""
    return plot_windows(path, traces, windows, 0, "degrees", [(180.0, ":")],
                        "The knees' angle between thigh and shin, the two legs' mean "
                        "(dotted: straight)")


def steps(motion: np.ndarray, layout: MotionLayout, stance: np.ndarray | None) -> dict[str, float]:
    """The feet's steps a window, the share lasting the data's step, and the stance's lifts a
    window (when the decoding steps by a stance)."""
    found = [foot_steps(layout.joint_positions(x, list(FEET))) for x in motion]
    lengths = np.asarray([end - start for clip in found for foot in clip for start, end in foot])
    out = {"steps": len(lengths) / len(motion),
           "data steps": float(np.mean(lengths == STANCE_SWING_FRAMES)) if len(lengths) else 0.0}
    if stance is not None:
        lifted = np.concatenate([np.zeros_like(stance[:, :1]), ~stance], axis=1).astype(int)
        out["lifts"] = float((np.diff(lifted, axis=1) == 1).sum()) / len(stance)
    return out


def head_angles(motion: np.ndarray, users: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """Each window's Head Ang. (sarah-eval's: the mean gaze score toward the user), (windows,)."""
    from sarah_data import icosahedron
    from sarah_models.evaluation.metrics.spec import MetricsConfig

    head = layout.joint(MetricsConfig().head_joint)
    out = []
    for x, user in zip(motion, users):
        position, rotation = icosahedron.decode(layout.split(x.astype(np.float64))[0][:, head])
        out.append(head_angle(position, rotation, user))
    return np.asarray(out)


def gaze(angles: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Head Ang. beside the data's on the same windows, and the look-away share (sarah-eval's)."""
    return {"head": float(np.mean(angles - truth)),
            "look-away": float(np.mean([looks_away(a) for a in angles]))}


def row(label: str, decoding: str, f: dict) -> str:
    shown = {key: f"{f[key]:.0f}" if np.isfinite(f.get(key, np.nan)) else "-"
             for key in (f"{p} {kind}" for p in ("shell", *PARTS) for kind in ("batch", "pooled"))}
    if "shell interval" in f:
        shown["shell batch"] += " ({:.0f}-{:.0f})".format(*f["shell interval"])
    cells = [" / ".join(shown[f"{p} {kind}"] for p in ("shell", *PARTS))
             for kind in ("batch", "pooled")]
    lifts = f"{f['lifts']:.1f}" if "lifts" in f else "-"
    head = (f"{f['head']:+.3f} | {f['look-away']:.2f}" if "head" in f else "- | -")
    return (f"| {label} | {decoding} | {cells[0]} | {cells[1]} | {f['steps']:.1f} | "
            f"{f['data steps']:.0%} | {lifts} | {head} |")


def decoding_of(settings: list[str]) -> str:
    """How the tables name a decoding: its ``--try`` settings, or the model's own."""
    return ", ".join(settings) or "the model's"


def check_tries(parser: argparse.ArgumentParser, tries: list[list[str]], config: RunConfig) -> None:
    """Each ``--try`` is decoding settings the model's ``config`` takes (parser.error naming the
    first that is not), checked there because a setting may need another the model sets
    (vae.root_hold_turn needs vae.root_hold); before anything is recorded or replayed."""
    for settings in tries:
        try:
            if not settings:
                raise ValueError("no setting given")
            model_file.with_decoding(config, settings)
        except ValueError as exc:
            parser.error(f"--try {','.join(settings)!r}: {exc}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--run", required=True, help="a run folder or model file")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--record", type=Path, metavar="NPZ",
                        help="record the decodes of --shards to this file, then replay them")
    source.add_argument("--replay", type=Path, metavar="NPZ", help="replay a recorded file")
    parser.add_argument("--shards", type=Path, help="shards folder (sarah-prep), with --record")
    parser.add_argument("--split", default="test", help="split whose windows are recorded")
    parser.add_argument("--windows", type=int, default=96, help="evenly spaced windows recorded")
    parser.add_argument("--window", type=int, default=400, help="frames per window")
    parser.add_argument("--try", dest="tries", action="append", default=[], metavar="SETTINGS",
                        help="decoding settings to replay with, e.g. vae.root_hold=0.15 or "
                             "vae.foot_lock=0.2,vae.root_hold=0.1 (repeatable)")
    parser.add_argument("--anatomy", action="store_true",
                        help=f"also print each body part's FGD_acc beside the real floor's (the "
                             f"recording's two halves of windows, from {2 * BATCH} windows), and its "
                             f"seam share and acceleration energy below and above {BAND_HZ:g} Hz "
                             f"against the data's")
    parser.add_argument("--stages", action="store_true",
                        help=f"also print, for each decoding, the shell's FGD_acc and each body "
                             f"part's seam share and acceleration energy below and above "
                             f"{BAND_HZ:g} Hz after each filter of the decoding chain in turn, "
                             f"the decoder's own frames first: what each filter adds and takes")
    parser.add_argument("--stages-plot", type=Path, metavar="PNG",
                        help="also draw the stages' table as a figure to this PNG (implies --stages)")
    parser.add_argument("--legs", action="store_true",
                        help=f"also print the legs' FGD_acc by the leg joints their points lie "
                             f"nearest to (the hips, each knee and ankle, both, and both less "
                             f"each alone: what lies between the two legs) beside the real floor's "
                             f"(from {2 * BATCH} windows), and the correlation of the left and "
                             f"right knees' and ankles' accelerations")
    parser.add_argument("--covariance", action="store_true",
                        help=f"also print the shell's and each body part's FGD_acc split into "
                             f"what the accelerations' spread accounts for with the data's "
                             f"principal axes (spectrum) and what the axes' directions add "
                             f"(orientation), with its energy ÷ the data's, beside the real "
                             f"floor's (from {2 * BATCH} windows)")
    parser.add_argument("--gait", action="store_true",
                        help=f"also print how the body walks: the pelvis's moves on the floor "
                             f"(faster than {PELVIS_MOVE_SPEED:g} m/s: how many a window, how long, "
                             f"how far, how fast), the share of frames both feet step, and the "
                             f"share of the pelvis's acceleration where no foot steps")
    parser.add_argument("--gait-plot", type=Path, metavar="PNG",
                        help=f"also draw the pelvis's speed on the floor, frame by frame, in "
                             f"{GAIT_PLOT_WINDOWS} windows, to this PNG (implies --gait)")
    parser.add_argument("--feet", action="store_true",
                        help=f"also print how far apart the feet stand: the shares of frames whose "
                             f"ankles come within {NEAR * 100:g} cm, whose gap along the hips' "
                             f"line is below {GAP * 100:g} cm (the foot lock's vae.foot_gap) and "
                             f"below 0 (crossed), the gap's percentiles, how far the ankles "
                             f"stand from under their hips, and the knees' angle")
    parser.add_argument("--feet-plot", type=Path, metavar="PNG",
                        help=f"also draw that gap frame by frame in the {FEET_PLOT_WINDOWS} windows "
                             f"where the decodings' feet come nearest, to this PNG (implies --feet)")
    parser.add_argument("--knees-plot", type=Path, metavar="PNG",
                        help=f"also draw the knees' angle frame by frame in {GAIT_PLOT_WINDOWS} "
                             f"windows (the first, the middle, the last), to this PNG (implies "
                             f"--feet)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_sampling_arguments(parser, EvalConfig())
    parser.add_argument("--seed", type=int, default=EvalConfig().seed, help="sarah-eval's --seed")
    args = parser.parse_args(argv)
    import torch

    from sarah_models.generation.run import GenerateError, load_run

    torch.set_num_threads(args.threads)
    try:  # first: the --try settings are checked on the model's config
        models, source = load_run(args.run, None, device="cpu", need_flow=True)
    except GenerateError as exc:
        parser.error(str(exc))
    tries = [[s.strip() for s in t.split(",") if s.strip()] for t in args.tries]
    check_tries(parser, tries, models.config)
    for flag, picture in (("--stages-plot", args.stages_plot), ("--gait-plot", args.gait_plot),
                          ("--feet-plot", args.feet_plot), ("--knees-plot", args.knees_plot)):
        if picture is not None and picture.suffix.lower() != ".png":
            parser.error(f"{flag} {picture}: the figure is a PNG (name it .png)")
        if picture is not None and not picture.parent.is_dir():
            parser.error(f"{flag} {picture}: no such folder {picture.parent}")
    args.stages |= args.stages_plot is not None
    args.gait |= args.gait_plot is not None
    args.feet |= args.feet_plot is not None or args.knees_plot is not None
    if args.record is not None and args.shards is None:
        parser.error("--record needs --shards")
    if args.replay is not None and not args.replay.is_file():
        parser.error(f"--replay {args.replay}: no such file")
    if args.windows < 1:
        parser.error(f"--windows must be at least 1, got {args.windows}")
    if args.record is not None:
        sampling = sampling_of(args, EvalConfig(seed=args.seed))
        recorded = record(models, args.shards, args.split, args.windows, sampling, args.window)
        with atomic_path(args.record) as tmp, open(tmp, "wb") as handle:
            np.savez(handle, **recorded)
        print(f"recorded {len(recorded['gt'])} windows to {args.record}")
    else:
        with np.load(args.replay, allow_pickle=False) as data:
            recorded = {key: data[key] for key in data.files}
    truth = recorded["gt"]
    layout = MotionLayout.from_width(truth.shape[-1])
    ico, shell = layout.split(truth[0, 0])
    parts = shell_parts(ico, shell, layout.joint_names)
    print(f"\n{len(truth)} windows; FGD_acc ×10^5 (cm/s²)², shell / legs / feet; foot steps: "
          f"runs of frames a foot moves faster than the foot slide's speed\n")
    users = recorded.get("user")  # recordings before the seventy-seventh run have none
    truth_angles = None if users is None else head_angles(truth, users, layout)
    print("| motion | decoding | FGD_acc per batch of 16 (shell's 95 %) | FGD_acc pooled | foot steps a window | "
          f"lasting {STANCE_SWING_FRAMES} frames | stance lifts a window | Head Ang. − GT | "
          "look-away |\n|---|---|---|---|---|---|---|---|---|")
    print(row("ground truth", "-", {**steps(truth, layout, None),
                                    **({} if users is None else gaze(truth_angles, truth_angles))}))
    real = shell_accelerations(truth, layout)
    stride = models.vae.config.stride
    truth_parts = anatomy(truth, real, layout, parts, stride) if args.anatomy or args.stages else None
    anatomies = [("ground truth", "-", truth_parts)] if args.anatomy else []
    by_stage = []
    floor = real_floor(real, parts) if args.anatomy else None
    by_part = [] if floor is None else [("real floor", "-", floor)]
    halves = real_halves(real)
    if args.covariance:
        covariances = [] if halves is None else [
            covariance_row("real floor", "-", covariance_terms(*halves, parts))]
    if args.gait:
        drawn = evenly_spaced(len(truth))
        walked = gait(truth, layout)
        gaits, traces = [gait_row("ground truth", "-", walked)], [("ground truth", "-", walked["paths"][drawn])]
    if args.feet:
        apart = feet_apart(truth, layout)
        feet, gaps = [feet_row("ground truth", "-", apart)], [("ground truth", "-", apart["gap"])]
        knees = [("ground truth", "-", apart["knee"].mean(axis=-1))]
    if args.legs:
        groups = leg_groups(ico, shell, layout)
        legs = [legs_row("ground truth" if halves is None else "real floor", "-",
                         None if halves is None else leg_distances(*halves, groups),
                         leg_correlations(truth, layout))]
    for settings in [[], *tries]:
        tried = tried_models(models, source, settings)
        for label in ROWS:
            frames, stance = recorded[f"{label}_frames"], recorded[f"{label}_stance"]
            if args.stages:  # the chain a filter at a time; its last stage is the decoded motion
                for stage, motion in stages(tried, frames, stance, users):
                    acc = shell_accelerations(motion, layout)
                    by_stage.append((
                        label, decoding_of(settings), stage,
                        np.asarray(batch_distances(acc, real, np.arange(real.shape[2]))),
                        anatomy(motion, acc, layout, parts, stride)))
            else:
                motion = decode(tried, frames, stance, users)
                acc = shell_accelerations(motion, layout)
            batches = part_distances(acc, real, parts) if args.anatomy else None
            figures = {**distances(acc, real, parts, batches),
                       **steps(motion, layout, stance if reads_stance(tried.vae) else None),
                       **({} if users is None else gaze(head_angles(motion, users, layout), truth_angles))}
            decoding = decoding_of(settings)
            print(row(label, decoding, figures), flush=True)
            if args.covariance:
                covariances.append(covariance_row(label, decoding, covariance_terms(acc, real, parts)))
            if args.gait:
                walked = gait(motion, layout)
                gaits.append(gait_row(label, decoding, walked))
                traces.append((label, decoding, walked["paths"][drawn]))
            if args.feet:
                apart = feet_apart(motion, layout)
                feet.append(feet_row(label, decoding, apart))
                gaps.append((label, decoding, apart["gap"]))
                knees.append((label, decoding, apart["knee"].mean(axis=-1)))
            if args.legs:
                legs.append(legs_row(label, decoding, leg_distances(acc, real, groups),
                                     leg_correlations(motion, layout)))
            if args.anatomy:
                anatomies.append((label, decoding, by_stage[-1][4] if args.stages else
                                  anatomy(motion, acc, layout, parts, stride)))
                by_part.append((label, decoding, batches))
    if args.anatomy:
        print(f"\nFGD_acc by body part, per batch of {BATCH} (95 % bootstrap over batches)"
              + (", and ÷ the real floor's: the data's first half of windows against its "
                 "second half\n" if floor is not None else
                 f"; no real floor: it needs {2 * BATCH} windows, the recording has "
                 f"{len(truth)}\n"))
        print("| motion | decoding | " + " | ".join(("shell", *parts))
              + " |\n|---|---|" + "---|" * (len(parts) + 1))
        for label, decoding, found in by_part:
            print(parts_row(label, decoding, found, floor))
        print(f"\nBy body part: seam share (the share of the acceleration on the second "
              f"differences centred on a latent block's last or first frame; {2 / stride:.2f} "
              f"without seams) / acceleration energy below / above {BAND_HZ:g} Hz (the "
              f"{BAND_FRAMES}-frame average's and the rest), ÷ the data's on the same windows; "
              f"95 % bootstrap intervals over the {len(truth)} windows, paired\n")
        print("| motion | decoding | " + " | ".join(truth_parts) + " |\n|---|---|"
              + "---|" * len(truth_parts))
        for label, decoding, found in anatomies:
            print(anatomy_row(label, decoding, found, truth_parts))
    if args.legs:
        print(f"\nThe legs' FGD_acc by the leg joints their shell points lie nearest to, per "
              f"batch of {BATCH} (95 % bootstrap over batches; the real floor: the data's first "
              f"half of windows against its second half, from {2 * BATCH} windows), and the "
              f"correlation of the left and right joints' accelerations, pooled over every "
              f"window's frames\n")
        pairs = " / ".join(f"{joint} {'xyz'[axis]}" for joint, axis in LEG_PAIRS)
        print("| motion | decoding | " + " | ".join(LEG_COLUMNS) + f" | left / right: {pairs} |\n"
              + "|---|---|" + "---|" * (len(LEG_COLUMNS) + 1))
        print("\n".join(legs))
    if args.gait:
        print(f"\nHow the body walks: the pelvis's moves on the floor (runs of frames it moves "
              f"faster than {PELVIS_MOVE_SPEED:g} m/s; a move's figures are medians over moves), "
              f"and its acceleration against the feet's steps (the steps column's)\n")
        print("| motion | decoding | " + " | ".join(GAIT_COLUMNS) + " |\n|---|---|"
              + "---|" * len(GAIT_COLUMNS))
        print("\n".join(gaits))
        if args.gait_plot is not None:
            print(f"\nwrote {plot_gait(args.gait_plot, traces, drawn)}")
    if args.covariance:
        print(f"\nFGD_acc by body part, per batch of {BATCH} (each term's mean over batches), "
              f"as spectrum + orientation: the distance the accelerations' covariances keep with "
              f"their principal axes aligned (their spread: how much energy, in how many "
              f"directions), and what the axes' directions add (which points accelerate "
              f"together, and which way); then the energy ÷ the data's"
              + ("" if halves is not None else
                 f"; no real floor: it needs {2 * BATCH} windows, the recording has {len(truth)}")
              + "\n")
        print("| motion | decoding | " + " | ".join(("shell", *parts))
              + " |\n|---|---|" + "---|" * (len(parts) + 1))
        print("\n".join(covariances))
    if args.feet:
        print(f"\nHow far apart the feet stand: frames whose ankles come within {NEAR * 100:g} cm "
              f"on the floor, whose gap along the hips' line (left ankle from right) is below "
              f"{GAP * 100:g} cm and below 0 (crossed), in % of frames with 95 % bootstrap "
              f"intervals over the {len(truth)} windows; the gap's percentiles over every frame; "
              f"how far the ankles stand from under their hips (each window's median, the mean "
              f"over windows with its 95 % interval; the 90th percentile over every frame), and "
              f"the knees' angle (each window's median, 180 straight)\n")
        print("| motion | decoding | " + " | ".join(FEET_COLUMNS) + " |\n|---|---|"
              + "---|" * len(FEET_COLUMNS))
        print("\n".join(feet))
        if args.feet_plot is not None:
            drawn = nearest_windows([gap for _, _, gap in gaps[1:]])
            print(f"\nwrote {plot_feet(args.feet_plot, [(a, b, gap[drawn]) for a, b, gap in gaps], drawn)} "
                  f"(windows {', '.join(map(str, drawn))})")
        if args.knees_plot is not None:
            drawn = evenly_spaced(len(truth))
            print(f"\nwrote {plot_knees(args.knees_plot, [(a, b, k[drawn]) for a, b, k in knees], drawn)} "
                  f"(windows {', '.join(map(str, drawn))})")
    if args.stages:
        print(f"\nBy stage of the decoding chain: the decoder's frames, then the motion after each "
              f"filter in turn; the shell's FGD_acc per batch of {BATCH} (95 % bootstrap over "
              f"batches), then by body part as above: seam share / acceleration energy below / "
              f"above {BAND_HZ:g} Hz ÷ the data's, paired over the {len(truth)} windows\n")
        print("| motion | decoding | after | FGD_acc (shell) | " + " | ".join(truth_parts)
              + " |\n|---|---|---|---|" + "---|" * len(truth_parts))
        print("\n".join(stage_row(*entry, truth_parts) for entry in by_stage))
    if args.stages_plot is not None:
        print(f"\nwrote {plot_stages(args.stages_plot, stage_series(by_stage, truth_parts))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
