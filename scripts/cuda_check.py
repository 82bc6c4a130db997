"""The CUDA path end to end, on a machine with a GPU (docs/performance.md, the CUDA entries):

    python scripts/cuda_check.py WORK_DIR [--report FILE.json]

1. fixture dyads (seed 0), prepped with the audio features on CUDA and on the CPU: are the
   shards the same bytes?
2. the tiny preset trained on CUDA, both stages: steps/s and peak GPU memory;
3. that run and the shipped ``fixture-tiny`` generating on CUDA and on the CPU, streamed and
   offline: the largest joint difference between the two devices (noise is drawn on the CPU,
   so they differ by kernel rounding only), and the chunk latency on each;
4. paper size (the paper's layers and widths, batch 16 of T = 400 frames per GPU as in A.2):
   training steps of each stage (steps/s, peak GPU memory), then streaming at 8 NFE, CFG 1.3
   from those weights (chunk latency p50/p99, fps) in the fp32 and bf16 inference modes.

Not run in CI (CI has no GPU); every figure it prints comes from this run, on this machine.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from sarah_models.config import StreamConfig
from sarah_models.generation.run import run as generate
from sarah_models.pretrained import model_path


def cli(*args: str, log: Path) -> float:
    """Run ``python -m sarah_cli.<args>``, output to ``log``; wall seconds. Fails loudly."""
    tick = time.perf_counter()
    with open(log, "w") as fh:
        done = subprocess.run([sys.executable, "-m", *args], stdout=fh, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        sys.exit(f"cuda_check: {' '.join(args[:2])} failed (rc {done.returncode}); see {log}:\n"
                 + log.read_text()[-3000:])
    return time.perf_counter() - tick


def shard_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.h5"))}


def shards_compare(cuda: Path, cpu: Path) -> dict:
    import h5py

    a, b = shard_bytes(cuda), shard_bytes(cpu)
    same = [name for name in a if b.get(name) == a[name]]
    worst = 0.0
    for name in a:
        if name in same or name not in b:
            continue
        with h5py.File(cuda / name) as fa, h5py.File(cpu / name) as fb:
            def visit(key, item):
                nonlocal worst
                if isinstance(item, h5py.Dataset) and item.dtype.kind == "f" and key in fb:
                    worst = max(worst, float(np.max(np.abs(item[()] - fb[key][()]), initial=0.0)))
            fa.visititems(visit)
    return {"files": len(a), "byte_identical": len(same), "max_abs_float_difference": worst}


def train_figures(run: Path, stage: str) -> dict:
    rows = [json.loads(line) for line in (run / f"{stage}_log.jsonl").read_text().splitlines()]
    last = rows[-1]  # the first interval holds cuDNN's autotuning and the allocator's growth
    return {"steps": last["step"], "steps_per_s": round(last["steps_per_s"], 2),
            "cuda_peak_gib": round(last.get("cuda_peak_gib", float("nan")), 2),
            "loss": round(last["loss"], 4)}


def generation(model: Path, shards: Path, out: Path, frames: int, offline: bool, device: str,
               speed: str = "fp32") -> tuple[np.ndarray, dict]:
    summary = generate(model, out, StreamConfig(), device=device, shards=shards, split="test",
                       frames=frames, offline=offline, animation=False, speed=speed,
                       echo=lambda _line: None)
    joints = np.load(out / "motion.npz", allow_pickle=False)["joint_positions"]
    figures = {"fps": round(summary.fps, 1)}
    if summary.latency_p50_ms is not None:
        figures.update(p50_ms=round(summary.latency_p50_ms, 2),
                       p99_ms=round(summary.latency_p99_ms, 2), chunks=summary.chunks)
    return joints, figures


def device_pair(name: str, model: Path, shards: Path, work: Path, frames: int, device: str) -> dict:
    """The same model and window on ``device`` and on the CPU, streamed and offline."""
    out = {}
    for offline in (False, True):
        mode = "offline" if offline else "streamed"
        gpu, gpu_fig = generation(model, shards, work / f"{name}-{mode}-cuda", frames, offline, device)
        cpu, cpu_fig = generation(model, shards, work / f"{name}-{mode}-cpu", frames, offline, "cpu")
        gap = np.linalg.norm(gpu - cpu, axis=-1) * 1000.0
        out[mode] = {device: gpu_fig, "cpu": cpu_fig, "max_joint_mm": round(float(gap.max()), 3),
                     "mean_joint_mm": round(float(gap.mean()), 4)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--report", type=Path, default=None)
    parser.add_argument("--tiny-steps", type=int, default=200)
    parser.add_argument("--paper-steps", type=int, default=30)
    parser.add_argument("--frames", type=int, default=400, help="frames per generated window")
    parser.add_argument("--device", default="cuda",
                        help="the device checked against the CPU ('cpu' rehearses the script)")
    args = parser.parse_args()
    device = args.device
    if device == "cuda" and not torch.cuda.is_available():
        sys.exit("cuda_check: no CUDA device here")
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    report = {"device": torch.cuda.get_device_name() if device == "cuda" else device,
              "torch": torch.__version__,
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}

    def save() -> None:
        print(json.dumps(report, indent=1), flush=True)
        if args.report:
            args.report.write_text(json.dumps(report, indent=1))

    def attempt(key: str, step) -> None:
        """One check; a failure is a finding, recorded, and the later checks still run."""
        try:
            report[key] = step()
        except Exception as error:  # noqa: BLE001 -- the report names it
            import traceback

            report[key] = {"error": f"{type(error).__name__}: {error}",
                           "where": traceback.format_exc().splitlines()[-6:]}
        save()

    raw, shards = work / "raw", work / "shards"
    report["fixtures_s"] = round(cli("sarah_cli.fixtures", str(raw), "--sessions", "4", "--seconds",
                                     "60", "--seed", "0", "--quiet", log=work / "fixtures.log"), 1)
    report["prep_cuda_s"] = round(cli("sarah_cli.prep", str(raw), str(shards), "--device", device,
                                      "--no-progress", log=work / "prep-cuda.log"), 1)
    report["prep_cpu_s"] = round(cli("sarah_cli.prep", str(raw), str(work / "shards-cpu"),
                                     "--device", "cpu", "--no-progress", log=work / "prep-cpu.log"), 1)
    report["shards_cuda_vs_cpu"] = shards_compare(shards, work / "shards-cpu")
    save()

    tiny = work / "runs" / "tiny"
    report["tiny_train_s"] = round(cli("sarah_cli.train", "--stage", "all", "--config", "tiny",
                                       "--shards", str(shards), "--out", str(tiny), "--device", device,
                                       "--steps", str(args.tiny_steps), "--no-progress",
                                       log=work / "train-tiny.log"), 1)
    report["tiny_train"] = {stage: train_figures(tiny, stage) for stage in ("vae", "flow")}
    attempt("tiny_run_vs_cpu",
            lambda: device_pair("tiny", tiny, shards, work / "gen", args.frames, device))
    attempt("shipped_vs_cpu", lambda: device_pair("shipped", model_path("fixture-tiny"), shards,
                                                  work / "gen", args.frames, device))

    paper = work / "runs" / "paper"
    report["paper_train_s"] = round(cli(
        "sarah_cli.train", "--stage", "all", "--config", "paper", "--shards", str(shards),
        "--out", str(paper), "--device", device, "--steps", str(args.paper_steps), "--no-progress",
        "--set", "train.audio_features=logmel", "--set", "train.log_every=10",
        "--set", "train.latent_stats_batches=8", log=work / "train-paper.log"), 1)
    report["paper_train"] = {stage: train_figures(paper, stage) for stage in ("vae", "flow")}
    for speed in ("fp32", "bf16"):
        attempt(f"paper_streamed_{speed}", lambda: generation(
            paper, shards, work / "gen" / f"paper-{speed}", args.frames, False, device, speed)[1])
    attempt("paper_offline_fp32", lambda: generation(
        paper, shards, work / "gen" / "paper-offline", args.frames, True, device)[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
