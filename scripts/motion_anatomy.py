"""Where a model's motion differs from the ground truth's: root against pose, which joints carry
the acceleration, how far the body travels, whether the feet step (docs/results.md, seventeenth
run). Streams the model (as sarah-eval's model row, g = none) on every 400-frame window of a
split and prints nine tables:

    python scripts/motion_anatomy.py --pretrained fixture-tiny --shards test_shards --split train
    # a model at its own sampling setting (sarah-eval's flags of the same names)
    python scripts/motion_anatomy.py --run model.safetensors --shards test_shards --split train \
        --noise-scale 0.3 --cfg 4.5 --guide user_head --guidance-interval 0,0.75 \
        --imputation trajectory

1. FGD (pooled), FGD_acc and foot slide of hybrids: the ground truth's pose on the model's root
   trajectory, and the model's pose on the ground truth's root; what each part costs;
2. the shell's acceleration energy per frame and its share by nearest body joint;
3. the root's path per window and its speed;
4. the feet: height percentiles, steps per window and foot, frames per step, how far a
   step carries the foot, and the median step's rise and travel per frame (docs/results.md,
   twenty-sixth run);
5. where the acceleration energy lies in frequency (the shell's, by band; the joints', by body
   part), for the model and for its VAE reconstructing the ground truth, each against the
   ground truth's (docs/results.md, nineteenth run): what FGD_acc weighs, and which of the
   two, VAE or flow, loses it;
6. the flow's latents in frequency: the power of the sampled latents (streamed, and offline on
   the same windows and seeds) in each band of token rate, against the encoder's latents of the
   ground truth, and how far each moves from one token to the next (docs/results.md, twentieth
   run): where the two protocols part;
7. FGD_acc by body part, as sarah-eval scores it (``metrics.body_parts``: batches of 16 clips,
   their mean, a bootstrap interval over batches, on the shell points nearest each joint
   group's joints), for the model (streamed and offline) and for its VAE, with each part's
   acceleration energy against the ground truth's (docs/results.md, twenty-fourth run): which
   part of the body the distance is in;
8. the decoding chain's own steps: the ground truth with its knees, ankles and feet carried
   rigidly with the pelvis (feet that glide, as a decoder's do, under the data's own path),
   through the model's decoding chain; FGD_acc of the whole shell, the legs and the feet, and
   foot slide
   (docs/results.md, fifty-first run): how far the foot lock's steps are from the data's where
   everything else is the data's;
9. by role and direction: the windows where the ground truth's agent walks (its pelvis's mean
   floor speed at least ``WALKER_SPEED``) and those where it stands, each motion's pelvis speed
   there, and the acceleration of the root, legs and feet split along the user's bearing
   (radial: toward or away from the user's head on the floor; tangential: around them;
   vertical), as RMS with the energy's ratio to the ground truth's, and FGD_acc pooled over
   each role's windows (docs/results.md, sixty-eighth run): whether the distance is in what the
   body does or in which role it does it.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from sarah_cli.arguments import add_sampling_arguments, sampling_of
from sarah_data import icosahedron
from sarah_data.constants import BODY_JOINTS, FPS, JOINT_NAMES
from sarah_data.frames import rotation_about_y, yaw_of
from sarah_data.skeleton import FEET, JOINT_GROUPS, ROOT, MotionLayout, shell_parts
from sarah_models.evaluation.metrics import (MetricsTable, evaluate, foot_slide, foot_steps,
                                             step_paths, step_reaches)
from sarah_models.evaluation.metrics.body_parts import part_key
from sarah_models.evaluation.metrics.clips import accelerations, floor_path
from sarah_models.evaluation.metrics.frechet import frechet_distance
from sarah_models.evaluation.metrics.pelvis_speed import pelvis_speed
from sarah_models.evaluation.metrics.radial_speed import toward_user
from sarah_models.evaluation.metrics.spec import FOOT_MAX_HEIGHT, FOOT_MIN_SPEED, MetricsConfig
from sarah_models.evaluation.metrics.table import bootstrap_interval
from sarah_models.evaluation.runner import EvalConfig
from sarah_models.evaluation.tables import MethodResult
from sarah_models.evaluation.windows import motion_clip
from sarah_models.sampling.foot_lock import SWING_FRAMES

BANDS = ((0, 2), (2, 4), (4, 6), (6, 8), (8, 10), (10, FPS / 2 + 1))  # Hz; the last holds Nyquist
BEATS = (2, 7)  # Hz: the fixtures' syllable-rate gestures (~4.5 Hz) and what blurs them
# What a decoder's gliding legs carry along with the pelvis: the legs below the hips, which ride
# the pelvis already.
GLIDING = tuple(name for name in JOINT_GROUPS["legs"] + JOINT_GROUPS["feet"]
                if not name.endswith("hip"))
# m/s: a window whose ground-truth pelvis moves this fast on average walks. The fixtures' roles
# part cleanly: their walking partner averages 0.45 m/s over a window, the standing one 0.06
# (the 296 seed-7 test windows, docs/results.md, sixty-eighth run).
WALKER_SPEED = 0.35
ROLE_PARTS = ("root", "legs", "feet")


def streamed_windows(models, shards: Path, split: str, sampling: EvalConfig = EvalConfig()):
    """(ground truth, model motion, user head, VAE reconstruction, latents, offline motion) of
    every window, ``models`` (``load_run``'s) streamed, generated offline and reconstructed as sarah-eval's model (both
    protocols) and VAE rows are; latents holds the standardized (K, Dz) latents "encoder" (of
    the ground truth), "stream" and "offline". Both protocols sample as ``sampling`` says
    (steps, guidance, noise, imputation; default: the paper's)."""
    import torch

    from sarah_data.dataset import WindowDataset
    from sarah_models.evaluation.runner import _vae_producer, window_generator

    windows = WindowDataset.sliding(shards, split, extractor=models.features, window=400)
    stream, offline = (window_generator(models, replace(sampling, protocol=p), None)
                       for p in ("stream", "offline"))
    reconstruct, nz = _vae_producer(models), models.normalizer
    out = []
    with torch.inference_mode():
        for i in range(len(windows)):
            item = windows[i]
            streamed, joint = stream(item, i), offline(item, i)
            mu, _ = models.vae.encode(nz.normalize("motion", item["motion"])[None])
            latents = {"encoder": nz.normalize("latent", mu[0]).numpy(),
                       "stream": streamed.latents, "offline": joint.latents}
            out.append((item["motion"].numpy().astype(np.float64),
                        streamed.motion.astype(np.float64), item["user_head"].numpy(),
                        reconstruct(item, i).astype(np.float64), latents,
                        joint.motion.astype(np.float64)))
    return out


def with_root(pose_of: np.ndarray, root_of: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """Every point of ``pose_of`` moved so that its root follows ``root_of``'s."""
    root = lambda m: layout.joint_positions(m, [ROOT])[:, 0]  # noqa: E731
    points = pose_of.reshape(len(pose_of), -1, 3) - root(pose_of)[:, None] + root(root_of)[:, None]
    return points.reshape(pose_of.shape)


def hybrids(clips, layout: MotionLayout) -> None:
    print("| clips | pooled FGD (÷10) | FGD_acc (÷1e5) | foot slide |\n|---|---|---|---|")
    gt = [motion_clip(g, u) for g, _, u, *_ in clips]
    for label, make in (("model", lambda g, m: m),
                        ("ground truth's pose on the model's root", lambda g, m: with_root(g, m, layout)),
                        ("model's pose on the ground truth's root", lambda g, m: with_root(m, g, layout))):
        table = evaluate([motion_clip(make(g, m), u) for g, m, u, *_ in clips], gt,
                         np.zeros(len(clips), bool), config=MetricsConfig(normalize_window=False))
        shown = MethodResult(label, label, True, None, table, None, False).shown()

        def cell(name: str, decimals: int) -> str:
            return (f"{shown[name + '/avg']:,.{decimals}f} ({shown[name + '/low']:,.{decimals}f}-"
                    f"{shown[name + '/high']:,.{decimals}f})")

        print(f"| {label} | {shown['fgd/pooled']:,.0f} | {cell('fgd_acc', 0)} | "
              f"{cell('foot_slide', 2)} |")

def energy(clips, layout: MotionLayout) -> None:
    print("\n| motion | shell acceleration energy per frame, (m/s²)² | largest shares by nearest joint |"
          "\n|---|---|---|")
    for label, index in (("ground truth", 0), ("model", 1)):
        total, by_joint = [], np.zeros(BODY_JOINTS)
        for clip in clips:
            motion = clip[index]
            a = accelerations(layout.split(motion)[1])
            e = np.sum(a ** 2, axis=-1)  # (T-2, P)
            total.append(e.sum(axis=1).mean())
            by_joint += np.bincount(nearest_body_joint(motion, layout), weights=e.mean(axis=0),
                                    minlength=BODY_JOINTS)
        top = np.argsort(by_joint)[::-1][:4]
        shares = ", ".join(f"{JOINT_NAMES[j]} {by_joint[j] / by_joint.sum():.2f}" for j in top)
        print(f"| {label} | {np.mean(total):,.0f} | {shares} |")


def travel(clips, layout: MotionLayout) -> None:
    print("\n| motion | root path per window, m | root speed p10 / p50 / p90, m/s |\n|---|---|---|")
    for label, index in (("ground truth", 0), ("model", 1)):
        paths, speeds = [], []
        for clip in clips:
            root = layout.joint_positions(clip[index], [ROOT])[:, 0, [0, 2]]
            speed = np.linalg.norm(np.diff(root, axis=0), axis=-1) * FPS
            paths.append(speed.sum() / FPS)
            speeds.append(speed)
        p = np.percentile(np.concatenate(speeds), [10, 50, 90])
        print(f"| {label} | {np.mean(paths):.2f} | {p[0]:.3f} / {p[1]:.3f} / {p[2]:.3f} |")


def feet(clips, layout: MotionLayout) -> None:
    print("\n| motion | foot height p5 / p50 / p95, cm | steps per window and foot | frames per step "
          "(median) | step length p10 / p50 / p90, cm | foot slide |\n|---|---|---|---|---|---|")
    shapes = {}
    for label, index in (("ground truth", 0), ("model", 1)):
        heights, steps, durations, reaches, slides, paths = [], [], [], [], [], []
        for clip in clips:
            p = layout.joint_positions(clip[index], list(FEET))
            heights.append(p[..., 1].ravel())
            found = foot_steps(p)
            for foot in found:
                steps.append(len(foot))
                durations += [end - start for start, end in foot]
            reaches += step_reaches(p, found)
            paths.append(step_paths(p, found, SWING_FRAMES))
            slides.append(foot_slide(layout.joint_positions(clip[index])))
        h = np.percentile(np.concatenate(heights), [5, 50, 95]) * 100
        r = np.percentile(reaches, [10, 50, 90]) * 100 if reaches else np.zeros(3)
        print(f"| {label} | {h[0]:.1f} / {h[1]:.1f} / {h[2]:.1f} | {np.mean(steps):.1f} | "
              f"{np.median(durations) if durations else 0:.0f} | {r[0]:.0f} / {r[1]:.0f} / {r[2]:.0f} | "
              f"{np.mean(slides):.2f} |")
        shapes[label] = np.concatenate(paths)
    print(f"\n(a foot steps while it moves faster than {FOOT_MIN_SPEED * 100:g} cm/s; it slides "
          f"when it does so below {FOOT_MAX_HEIGHT * 100:g} cm)")
    print(f"\nThe median step over the {SWING_FRAMES} frames after the last frame the foot stands "
          "(the foot lock's swing):\n\n| motion | steps | rise, cm | travel, % |\n|---|---|---|---|")
    for label, paths in shapes.items():
        if len(paths):
            rise, travel = np.median(paths, axis=0).T
            print(f"| {label} | {len(paths)} | {' '.join(f'{v * 100:.2f}' for v in rise)} | "
                  f"{' '.join(f'{v * 100:.0f}' for v in travel)} |")


def band_power(signals: np.ndarray, rate: float, bands) -> np.ndarray:
    """(T, ...) signals sampled at ``rate`` Hz -> the power of their deviation from their mean in
    each band [low, high) Hz, summed over every channel."""
    x = signals.reshape(len(signals), -1)
    power = (np.abs(np.fft.rfft(x - x.mean(axis=0), axis=0)) ** 2).sum(axis=1)
    freqs = np.fft.rfftfreq(len(x), 1.0 / rate)
    return np.array([power[(freqs >= low) & (freqs < high)].sum() for low, high in bands])


def band_energy(points: np.ndarray, bands=BANDS) -> np.ndarray:
    """The acceleration power of ``points`` (T, ...) in metres, in each band [low, high) Hz."""
    x = points.reshape(len(points), -1)
    return band_power(accelerations(x), FPS, bands)


def part_joints(names) -> dict[str, list[int]]:
    """Joint indices of each joint group (``JOINT_GROUPS``) among ``names``."""
    return {part: [names.index(name) for name in group if name in names]
            for part, group in JOINT_GROUPS.items()}


def spectrum(clips, layout: MotionLayout) -> None:
    sums = {}  # (motion index, what) -> band energies summed over clips
    parts = part_joints(layout.joint_names)
    for clip in clips:
        for index in (0, 1, 3):
            shell = layout.split(clip[index])[1]
            joints = layout.joint_positions(clip[index])
            rows = {"shell": band_energy(shell)}
            rows.update({part: band_energy(joints[:, js], BANDS + (BEATS,))
                         for part, js in parts.items()})
            for what, e in rows.items():
                sums[index, what] = sums.get((index, what), 0) + e
    gt_shell = sums[0, "shell"]
    row = lambda label, values: print(f"| {label} | " + " | ".join(values) + " |")  # noqa: E731
    row("shell acceleration, band (Hz)", [f"{lo:g}-{min(hi, FPS / 2):g}" for lo, hi in BANDS])
    print("|---|" + "---|" * len(BANDS))
    row("ground truth's share", [f"{e:.2f}" for e in gt_shell / gt_shell.sum()])
    for label, index in (("model / ground truth", 1), ("VAE / ground truth", 3)):
        row(label, [f"{e:.2f}" for e in sums[index, "shell"] / gt_shell])
    total = sum(sums[0, part][:len(BANDS)].sum() for part in parts)
    beats = f"{BEATS[0]:g}-{BEATS[1]:g} Hz"
    print()
    row("joints", ["share of the ground truth's energy", "model / GT", "VAE / GT", f"share in {beats}",
                   f"model / GT, {beats}", f"VAE / GT, {beats}"])
    print("|---|---|---|---|---|---|---|")
    for part in parts:
        gt, model, vae = (sums[i, part] for i in (0, 1, 3))
        whole, n = gt[:len(BANDS)].sum(), len(BANDS)
        row(part, [f"{x:.2f}" for x in (whole / total, model[:n].sum() / whole, vae[:n].sum() / whole,
                                        gt[-1] / total, model[-1] / gt[-1], vae[-1] / gt[-1])])


LATENT_BANDS = ((0, 0.2), (0.2, 0.5), (0.5, 1), (1, 2), (2, 3), (3, np.inf))  # Hz; the last holds Nyquist


def latent_band_power(latents: np.ndarray, token_rate: float, bands=LATENT_BANDS) -> np.ndarray:
    """(K, Dz) latents, one per token -> their power in each band [low, high) Hz."""
    return band_power(latents, token_rate, bands)


def latent_step(latents: np.ndarray) -> float:
    """The RMS change of a latent from one token to the next (per channel)."""
    return float(np.sqrt(np.mean(np.diff(latents, axis=0) ** 2)))


def latent_spectrum(clips, token_rate: float) -> None:
    kinds = ("encoder", "stream", "offline")
    power = {k: sum(latent_band_power(c[4][k], token_rate) for c in clips) for k in kinds}
    step = {k: np.mean([latent_step(c[4][k]) for c in clips]) for k in kinds}
    print("| latents | token-to-token change | " + " | ".join(
        f"{lo:g}-{min(hi, token_rate / 2):g} Hz" for lo, hi in LATENT_BANDS) + " |")
    print("|---|---|" + "---|" * len(LATENT_BANDS))
    print(f"| encoder (of the ground truth), power | {step['encoder']:.3f} | "
          + " | ".join(f"{e:.0f}" for e in power["encoder"]) + " |")
    for kind in ("stream", "offline"):
        print(f"| {kind} / encoder | {step[kind]:.3f} | "
              + " | ".join(f"{e:.2f}" for e in power[kind] / power["encoder"]) + " |")


def nearest_body_joint(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """Per shell point, the index of the body joint (of the first BODY_JOINTS) nearest it in
    ``motion``'s first frame."""
    icosahedra, shell = layout.split(motion[:1])
    joints = icosahedra[0].mean(axis=-2)[:BODY_JOINTS]
    return np.argmin(np.sum((shell[0][:, None] - joints[None]) ** 2, -1), axis=1)


def by_part(generated, truth, layout: MotionLayout, parts) -> MetricsTable:
    """sarah-eval's metrics of ``generated`` motions against ``truth`` (the same windows), FGD_acc
    by body part too (``parts``: ``body_parts.shell_parts``)."""
    clips = [[motion_clip(m, np.zeros((len(m), 2))) for m in motions] for motions in (generated, truth)]
    return evaluate(*clips, np.zeros(len(truth), bool),
                    config=MetricsConfig(normalize_window=False, shell_parts=parts))


def reference_parts(motion: np.ndarray, layout: MotionLayout) -> dict[str, tuple[int, ...]]:
    """The body parts' shell points, by ``motion``'s first frame (sarah-eval's rule)."""
    return shell_parts(*layout.split(motion[0]), layout.joint_names)


def fgd_acc_cell(table: MetricsTable, part: str | None = None) -> str:
    v = table.values["fgd_acc" if part is None else part_key(part)]
    scale = table.display_scale["fgd_acc"]
    return f"{v.avg / scale:,.0f} ({v.low / scale:,.0f}-{v.high / scale:,.0f})"


def acceleration_by_part(clips, layout: MotionLayout) -> None:
    truth = [c[0] for c in clips]
    parts = reference_parts(truth[0], layout)
    tables = [by_part([c[index] for c in clips], truth, layout, parts) for index in (1, 5, 3)]
    print("| shell points nearest | points | streamed FGD_acc (÷1e5) | streamed energy / GT | "
          "offline FGD_acc | offline energy / GT | VAE FGD_acc | VAE energy / GT |"
          "\n|---|---|---|---|---|---|---|---|")
    print(f"| whole shell | {layout.shell_points} | " + " | ".join(
        f"{fgd_acc_cell(t)} | -" for t in tables) + " |")
    for part, points in parts.items():
        print(f"| {part} | {len(points)} | " + " | ".join(
            f"{fgd_acc_cell(t, part)} | {t.values[part_key(part)].ratio:.2f}" for t in tables) + " |")


def gliding_legs(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """``motion`` with its knees, ankles and feet (their icosahedra, and the shell points nearest
    them in the first frame) carried rigidly with the pelvis from the first frame, turning as
    the pelvis turns: the legs of a decoder whose feet glide, under the data's
    own pelvis path. Everything else stays as it was."""
    out = np.array(motion, dtype=np.float64)
    icosahedra, shell = layout.split(out)  # views into ``out``
    joints = icosahedra.mean(axis=-2)
    legs = [j for j, name in enumerate(JOINT_NAMES[:BODY_JOINTS]) if name in GLIDING]
    points = np.flatnonzero(np.isin(nearest_body_joint(out, layout), legs))
    root = JOINT_NAMES.index(ROOT)
    yaw = yaw_of(icosahedron.decode(icosahedra[:, root])[1])  # the heading the window frame reads
    turn = rotation_about_y(yaw - yaw[0])  # (T, 3, 3)
    pelvis = joints[:, root]

    def carried(first: np.ndarray) -> np.ndarray:
        return pelvis[:, None] + np.einsum("tij,nj->tni", turn, first.reshape(-1, 3) - pelvis[0])

    icosahedra[:, legs] = carried(icosahedra[0, legs]).reshape(icosahedra[:, legs].shape)
    shell[:, points] = carried(shell[0, points])
    return out


def chain_steps(clips, layout: MotionLayout, decoding) -> None:
    """Table 8: the ground truth and its gliding legs through ``decoding()`` (a new stream's
    decoding chain; causal, so a whole window decodes as a stream's blocks do, as in
    sarah-eval's "decoded" row)."""
    truth, users = [c[0] for c in clips], [c[2] for c in clips]  # a turning hold reads the user
    gliding = [gliding_legs(m, layout) for m in truth]
    parts = reference_parts(truth[0], layout)
    print("| clips | FGD_acc (÷1e5) | legs FGD_acc | legs energy / GT | feet FGD_acc | feet energy / GT "
          "| foot slide (95 % over windows) |\n|---|---|---|---|---|---|---|")
    for label, motions in (("ground truth through the chain",
                            [decoding()(m, None, u) for m, u in zip(truth, users)]),
                           ("its legs gliding with the pelvis", gliding),
                           ("the same through the chain",
                            [decoding()(m, None, u) for m, u in zip(gliding, users)])):
        table = by_part(motions, truth, layout, parts)
        slides = [foot_slide(layout.joint_positions(m)) for m in motions]
        print(f"| {label} | {fgd_acc_cell(table)} | " + " | ".join(
            f"{fgd_acc_cell(table, p)} | {table.values[part_key(p)].ratio:.2f}" for p in ("legs", "feet"))
              + " | {:.4f} ({:.4f}-{:.4f}) |".format(np.mean(slides), *bootstrap_interval(slides)))


def along_bearing(a: np.ndarray, motion: np.ndarray, user_head: np.ndarray,
                  layout: MotionLayout) -> np.ndarray:
    """(T - 2, P, 3) accelerations ``a`` of ``motion``'s frames 1 to T - 2, as (radial,
    tangential, vertical): radial along the floor from the clip's pelvis toward the user's head
    (positive toward), tangential the floor direction 90 degrees from it, each at the frame's
    own bearing."""
    root = floor_path(layout.joint_positions(motion))[1:-1]
    unit = toward_user(root, np.asarray(user_head)[1:-1])
    rx, rz = unit[:, None, 0], unit[:, None, 1]
    return np.stack([a[..., 0] * rx + a[..., 2] * rz, a[..., 2] * rx - a[..., 0] * rz, a[..., 1]], -1)


def mean_floor_speed(motion: np.ndarray, layout: MotionLayout) -> float:
    """m/s: the pelvis's mean speed on the floor over a clip (sarah-eval's Pelvis Speed)."""
    return pelvis_speed(layout.joint_positions(motion))


def roles(clips, layout: MotionLayout) -> None:
    parts = {part: list(points) for part, points in reference_parts(clips[0][0], layout).items()
             if part in ROLE_PARTS}
    walks = np.array([mean_floor_speed(c[0], layout) >= WALKER_SPEED for c in clips])
    motions = (("ground truth", 0), ("model, streamed", 1), ("model, offline", 5),
               ("VAE reconstruction", 3))
    print(f"By role and direction ({walks.sum()} windows where the ground truth's agent walks, "
          f">= {WALKER_SPEED} m/s, {(~walks).sum()} where it stands): acceleration RMS along the "
          "user's bearing, cm/s², radial / tangential / vertical, [energy ÷ the ground truth's]")
    print("\n| role | motion | pelvis m/s | " + " | ".join(parts) + " | FGD_acc pooled (÷1e5) |"
          "\n|---|---|---|" + "---|" * (len(parts) + 1))
    for role, chosen in (("walks", walks), ("stands", ~walks)):
        picked = [c for c, keep in zip(clips, chosen) if keep]
        if not picked:
            continue
        truth = None
        for label, index in motions:
            # each clip's shell accelerations once: FGD_acc's samples (cm/s², the window frame)
            # and, turned onto the user's bearing, each part's energy
            shell = [accelerations(layout.split(c[index])[1]) for c in picked]
            turned = np.concatenate([along_bearing(a, c[index], c[2], layout)
                                     for a, c in zip(shell, picked)])
            energy = {part: np.mean(turned[:, points] ** 2, axis=(0, 1))
                      for part, points in parts.items()}
            samples = np.concatenate([100 * a.reshape(len(a), -1) for a in shell])
            speed = np.mean([mean_floor_speed(c[index], layout) for c in picked])
            cells, distance = [], "-"
            for part, e in energy.items():
                rms = " / ".join(f"{v:,.0f}" for v in 100 * np.sqrt(e))
                if truth is None:
                    cells.append(rms)
                    continue
                reference = truth[0][part]
                ratios = " / ".join(f"{v / r:.2f}" if r > 0 else "-" for v, r in zip(e, reference))
                cells.append(f"{rms} [{ratios}]")
            if truth is None:
                truth = (energy, samples)
            else:
                distance = f"{frechet_distance(samples, truth[1]) / 1e5:,.0f}"
            print(f"| {role} | {label} | {speed:.2f} | " + " | ".join(cells) + f" | {distance} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--run", help="a run folder or model file")
    source.add_argument("--pretrained", help="a shipped model, e.g. fixture-tiny")
    parser.add_argument("--shards", type=Path, required=True, help="shards folder (sarah-prep)")
    parser.add_argument("--split", default="test", help="split whose 400-frame windows are streamed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_sampling_arguments(parser, EvalConfig())
    args = parser.parse_args(argv)
    sampling = sampling_of(args, EvalConfig())
    if args.pretrained:
        from sarah_models.pretrained import model_path

        try:
            model = str(model_path(args.pretrained))
        except ValueError as exc:
            parser.error(str(exc))
    else:
        model = args.run
    import torch

    from sarah_models.generation.run import load_run
    from sarah_models.sampling.decoding import stream_decoding

    torch.set_num_threads(args.threads)
    models, _ = load_run(model, None, device="cpu", need_flow=True)
    clips = streamed_windows(models, args.shards, args.split, sampling)
    if not clips:
        print(f"{args.shards}: split {args.split!r} has no 400-frame windows", file=sys.stderr)
        return 2
    layout = MotionLayout.from_width(clips[0][0].shape[1])
    print(f"{len(clips)} windows of split {args.split!r} in {args.shards}, streamed, g = none, "
          f"{args.steps} steps, CFG {args.cfg} guiding {','.join(args.guide)} at "
          f"{args.guidance_interval[0]:g} <= tau < {args.guidance_interval[1]:g}, "
          f"noise {args.noise_scale}, "
          f"{args.imputation} imputation\n")
    hybrids(clips, layout)
    energy(clips, layout)
    travel(clips, layout)
    feet(clips, layout)
    spectrum(clips, layout)
    print()
    latent_spectrum(clips, FPS / (clips[0][0].shape[0] // len(clips[0][4]["encoder"])))
    print()
    acceleration_by_part(clips, layout)
    print()
    chain_steps(clips, layout, lambda: stream_decoding(models.vae, models.normalizer))
    print()
    roles(clips, layout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
