"""sarah-fixtures: generated dyads in the exact Embody 3D layout, with a separate truth file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_cli.arguments import HelpFormatter
from sarah_data.fixtures.dyads import FixtureConfig, make_fixtures


def build_parser() -> argparse.ArgumentParser:
    defaults = FixtureConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-fixtures", formatter_class=HelpFormatter,
        description="Write generated two-person sequences as Embody 3D lays them out: "
                    "OUT/aiagent/ (dataset.json + per-person .npy/.wav), OUT/body_models/ "
                    "(the procedural body model) and OUT/fixture_truth.json/.npz (what the "
                    "generator did: roles, gaze propensity, head yaw, speaking, steps, gestures).")
    parser.add_argument("out", type=Path, help="output folder (created if needed)")
    parser.add_argument("--sessions", type=int, default=defaults.sessions, help="capture sessions")
    parser.add_argument("--sequences-per-session", type=int, default=defaults.sequences_per_session,
                        help="dyad sequences per session")
    parser.add_argument("--seconds", type=float, default=defaults.seconds, help="length of each sequence")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="same seed, same bytes")
    parser.add_argument("--body-model", type=Path, default=None,
                        help="copy this SMPL-X-format .npz into OUT/body_models/ instead of writing "
                             "the procedural body model")
    parser.add_argument("--no-progress", "--quiet", dest="quiet", action="store_true",
                        help="no progress bar (--quiet is the same)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        print(f"sarah-fixtures: error: {args.out}: the output must be a folder, this is a file",
              file=sys.stderr)
        return 2
    try:
        summary = make_fixtures(args.out, sessions=args.sessions, seconds=args.seconds, seed=args.seed,
                                sequences_per_session=args.sequences_per_session,
                                progress=not args.quiet, body_model=args.body_model)
    except (ValueError, OSError) as error:
        print(f"sarah-fixtures: error: {error}", file=sys.stderr)
        return 2
    print(summary.line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
