"""sarah-eval: the paper's Table 1 (GT, Random, NN, model) and Table 2 (gaze sweep) on test windows."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_cli.arguments import (HISTORY_HELP, IMPUTATION_HELP, HelpFormatter, add_model_arguments,
                                 add_sampling_arguments, history_tokens,
                                 sampling_of)

EXIT_ERROR = 2


def _gazes(text: str) -> tuple[float | None, ...]:
    values = []
    for part in text.split(","):
        part = part.strip().lower()
        if part in ("none", "null", "off", "∅"):
            values.append(None)
            continue
        try:
            value = float(part)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"--gaze expects comma-separated numbers in [-1, 1] or 'none', got {part!r}") from None
        if not -1.0 <= value <= 1.0:
            raise argparse.ArgumentTypeError(f"--gaze values must be in [-1, 1], got {value:g}")
        values.append(value)
    if not values:
        raise argparse.ArgumentTypeError("--gaze needs at least one value")
    return tuple(values)


def _methods(text: str) -> tuple[str, ...]:
    return tuple(p.strip().lower() for p in text.split(",") if p.strip())


def build_parser() -> argparse.ArgumentParser:
    from sarah_models.evaluation.runner import EvalConfig

    d = EvalConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-eval", formatter_class=HelpFormatter,
        description="Evaluate GT, the Random and NN baselines and a trained run on a split's "
                    "non-overlapping T-frame windows (paper sec. 4 and A.2). Writes "
                    "table1.md/.json (Table 1, each row beside GT, and FGD_acc by body part), "
                    "table2.md/.json, with the model latents.md/.json (its sampled latents "
                    "against the encoder's), windows.json and plots/*.png to --out.")
    add_model_arguments(parser, required=False,
                        run_help="training run folder with flow.pt, or a model file (needed for "
                                 "the 'model' method)")
    parser.add_argument("--shards", type=Path, required=True, help="shards folder (sarah-prep)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--split", default=d.split, help="split evaluated")
    parser.add_argument("--windows", type=int, default=d.windows,
                        help="test windows evaluated (evenly spaced over the split; all when it "
                             "has fewer)")
    parser.add_argument("--window", type=int, default=d.window, help="frames per window (T)")
    parser.add_argument("--gaze", type=_gazes, default=",".join(
        "none" if g is None else f"{g:g}" for g in d.gaze),
        help="Table 2's gaze targets, comma-separated; 'none' disables gaze control")
    parser.add_argument("--table1-gaze", type=lambda t: _gazes(t)[0], default="none",
                        help="gaze target of the model's Table 1 row (the paper: none)")
    parser.add_argument("--methods", type=_methods, default=",".join(d.methods),
                        help="comma-separated subset of gt,real,random,nn,model (the paper's "
                             "Table 1 and the real-vs-real floor: other windows' ground truth) and vae (the run's VAE reconstructing the ground truth: the "
                             "floor under any flow sample; needs only vae.pt; adds "
                             "reconstruction.md, its error per body part in mm), decoded (the ground "
                             "truth through the run's decoding chain: the chain's own floor), "
                             "blur and jitter "
                             "(calibration: the ground truth through a moving average of "
                             "--blur-frames frames, or plus --jitter-mm of i.i.d. noise: what a "
                             "metric's value looks like)")
    parser.add_argument("--blur-frames", type=int, default=d.blur_frames,
                        help="frames of the blur row's centred moving average")
    parser.add_argument("--jitter-mm", type=float, default=d.jitter_mm,
                        help="standard deviation of the jitter row's noise, mm")
    parser.add_argument("--batch-clips", type=int, default=d.batch_clips,
                        help="clips per batch of the FGD / FGD_acc Avg column")
    parser.add_argument("--library-size", type=int, default=d.library_size,
                        help="training windows in the NN library and the Random pool")
    parser.add_argument("--library-shards", type=Path, default=None,
                        help="shards folder whose training split the Random pool and NN library "
                             "come from (default: --shards); for a test corpus the model never "
                             "saw, its training shards")
    parser.add_argument("--seed", type=int, default=d.seed,
                        help="seed of the baselines' draws and the model's noise")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    add_sampling_arguments(parser, d,
                           imputation_help=IMPUTATION_HELP + "; the offline protocol ignores it")
    parser.add_argument("--history", type=history_tokens, default=d.history_tokens,
                        help=HISTORY_HELP + "; the offline protocol ignores it")
    parser.add_argument("--protocol", choices=("offline", "stream"), default=d.protocol,
                        help="stream: 4 frames per step, as users run it; offline: all T frames "
                             "at once (causal mask), as the paper times FPS")
    parser.add_argument("--features", default=None,
                        help="audio features for the baselines when no model is evaluated "
                             "(default: logmel; with a model: the checkpoint's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sarah_data.loading import DataProblem
    from sarah_models.evaluation.runner import EvalConfig, EvalError, run_evaluation

    problems = [f"--shards {args.shards}: no such folder"] if not args.shards.is_dir() else []
    if args.out.exists() and not args.out.is_dir():
        problems.append(f"--out {args.out} is a file, not a folder")
    if args.device is not None:
        from sarah_data.config import device_problems

        problems += device_problems(args.device)
    if problems:  # before anything loads: the first line names the first problem
        print(f"sarah-eval: error: {problems[0]}", file=sys.stderr)
        return EXIT_ERROR
    try:
        config = sampling_of(args, EvalConfig(
            split=args.split, windows=args.windows, window=args.window, gaze=args.gaze,
            table1_gaze=args.table1_gaze, methods=args.methods, batch_clips=args.batch_clips,
            seed=args.seed, history_tokens=args.history, protocol=args.protocol,
            blur_frames=args.blur_frames, jitter_mm=args.jitter_mm,
            library_size=args.library_size, features=args.features,
            library_shards=None if args.library_shards is None else str(args.library_shards),
            device=args.device))
        result = run_evaluation(args.run, args.shards, args.out, config,
                                progress=not args.no_progress)
    except (EvalError, DataProblem) as exc:
        print(f"sarah-eval: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    for path in result.paths:
        if path.suffix == ".md":
            print(path.read_text(encoding="utf-8"))
    print("wrote " + ", ".join(str(p) for p in result.paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
