"""sarah-generate: stream the agent's motion from a trained run, with gaze guidance."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from sarah_cli.arguments import (HISTORY_HELP, HelpFormatter, add_model_arguments,
                                 add_sampling_arguments, history_tokens, positive_int,
                                 sampling_of)
from sarah_models.accel import MODE_HELP, MODES
from sarah_models.generation.run import SKELETONS

EXIT_ERROR = 2


def _gaze(text: str) -> float | None:
    if text.strip().lower() in ("none", "null", "off"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--gaze must be a number in [-1, 1] or 'none', got {text!r}") from None
    if not -1.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"--gaze must be in [-1, 1] or 'none', got {value:g}")
    return value


def _agent_start(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"--agent-start expects X,Z,YAW_DEG, got {text!r}")
    return values  # type: ignore[return-value]


def _betas(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(p) for p in text.split(","))
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"--betas expects comma-separated numbers, got {text!r}")
    return values


def _option(text: str) -> tuple[str, object]:
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--feature-option expects KEY=VALUE, got {text!r}")
    for cast in (int, float):
        try:
            return key, cast(raw)
        except ValueError:
            pass
    return key, raw


def build_parser() -> argparse.ArgumentParser:
    from sarah_models.config import StreamConfig

    d = StreamConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-generate", formatter_class=HelpFormatter,
        description="Generate the agent's motion causally, 4 frames at a time, from a trained run. "
                    "Inputs: a shard window (--shards --sequence --agent) or raw files "
                    "(--user-trajectory --agent-audio --user-audio). Writes motion.npz, "
                    "topview.png and skeleton.gif to --out.")
    add_model_arguments(parser, required=True,
                        run_help="training run folder (runs/NAME) or a model.safetensors file")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="checkpoint or model file (default: RUN/model.safetensors, else RUN/flow.pt)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--gaze", default=str(d.gaze),
                        help="target gaze score in [-1, 1], or 'none' to drop it")
    add_sampling_arguments(parser, d, steps_help="solver steps per chunk")
    parser.add_argument("--history", type=history_tokens, default=d.history_tokens,
                        help=HISTORY_HELP)
    parser.add_argument("--seed", type=int, default=d.seed,
                        help="noise seed: the same seed and inputs give the same motion (bit "
                             "for bit with the same --threads; other thread counts round "
                             "differently, ~1e-7 m)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    parser.add_argument("--offline", action="store_true",
                        help="the offline protocol: all tokens denoised jointly")
    parser.add_argument("--no-animation", action="store_true",
                        help="skip skeleton.gif (drawing it takes most of a short run)")
    parser.add_argument("--skeleton", choices=tuple(SKELETONS), default="agent",
                        help="whose bones the motion is decoded on: " + "; ".join(
                            f"{k}: {v}" for k, v in SKELETONS.items()))
    parser.add_argument("--body-model", type=Path, default=None,
                        help="a SMPL-X .npz: the agent is this model's body with --betas (an "
                             "avatar's), for raw inputs or in place of a shard window's person: "
                             "the motion is decoded on its bones and motion.npz carries it for "
                             "sarah-export")
    parser.add_argument("--betas", type=_betas, default=None,
                        help="B1,B2,...: the --body-model body's shape (default: zeros; fewer "
                             "than the model has are padded with zeros)")
    parser.add_argument("--speed", choices=MODES, default="fp32",
                        help="inference fast path: " + "; ".join(f"{k}: {v}" for k, v in MODE_HELP.items())
                             + " (int8 stays within 1 mm of fp32; see docs/performance.md)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="CPU intra-op threads (default: automatic, every core other "
                             "processes leave free, re-measured while streaming; give a count to "
                             "compare outputs bit for bit)")
    shard = parser.add_argument_group("shard input")
    shard.add_argument("--shards", type=Path, default=None, help="shards folder")
    shard.add_argument("--split", default="test", help="split of --shards to take the window from")
    shard.add_argument("--sequence", default=None, help="sequence name (default: the split's first)")
    shard.add_argument("--agent", default=None,
                       help="person generated as the agent (default: the sequence's first)")
    shard.add_argument("--start", type=int, default=None,
                       help="first frame; when not given, the first frame from which --frames "
                            "frames are tracked for both persons, in --sequence or the split's "
                            "first sequence that has such a run")
    shard.add_argument("--frames", type=int, default=None,
                       help="frames to generate (default: 400 from a shard, all for raw input)")
    raw = parser.add_argument_group("raw input")
    raw.add_argument("--user-trajectory", type=Path, default=None,
                     help="(T, 2) floor x, z of the user's head at 30 fps (.npy or .csv)")
    raw.add_argument("--agent-audio", type=Path, default=None, help="agent's audio file (any rate)")
    raw.add_argument("--user-audio", type=Path, default=None, help="user's audio file (any rate)")
    raw.add_argument("--pad", action="store_true",
                     help="pad audio shorter than the trajectory with silence (else an error)")
    raw.add_argument("--agent-start", type=_agent_start, default=(0.0, 0.0, 0.0),
                     help="agent's initial floor position and heading: X,Z,YAW_DEG")
    raw.add_argument("--feature-option", type=_option, action="append", default=[],
                     help="KEY=VALUE override of the audio extractor's config (e.g. a weights path)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sarah_data.loading import DataProblem
    from sarah_models.generation.run import GenerateError, run
    from sarah_models.config import StreamConfig

    try:
        config = sampling_of(args, StreamConfig(history_tokens=args.history,
                                                gaze=_gaze(args.gaze), seed=args.seed))
    except (ValueError, argparse.ArgumentTypeError) as exc:
        print(f"sarah-generate: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    problems = []
    if args.frames is not None and args.frames < 1:
        problems.append(f"--frames must be >= 1, got {args.frames}")
    if args.start is not None and args.start < 0:
        problems.append(f"--start must be >= 0, got {args.start}")
    if args.betas is not None and args.body_model is None:
        problems.append("--betas needs --body-model (the SMPL-X file whose shape they are)")
    if args.device is not None:
        from sarah_data.config import device_problems

        problems += device_problems(args.device)
    if problems:
        print(f"sarah-generate: error: {problems[0]}", file=sys.stderr)
        return EXIT_ERROR
    try:
        run(args.run, args.out, config, checkpoint=args.checkpoint, device=args.device,
            shards=args.shards, split=args.split, sequence=args.sequence, agent=args.agent,
            start=args.start, frames=args.frames, trajectory=args.user_trajectory,
            agent_audio=args.agent_audio, user_audio=args.user_audio,
            agent_start=args.agent_start, feature_options=dict(args.feature_option),
            offline=args.offline, animation=not args.no_animation, speed=args.speed, pad=args.pad,
            threads=args.threads, skeleton=args.skeleton, body_model=args.body_model,
            betas=args.betas)
    except (GenerateError, DataProblem) as exc:
        print(f"sarah-generate: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
