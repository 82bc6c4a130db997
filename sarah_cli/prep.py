"""sarah-prep: Embody 3D sections (or fixtures) to HDF5 shards; --verify and --info on shards."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from sarah_data.config import PrepConfig
from sarah_cli.arguments import HelpFormatter

EXIT_NOTHING_WRITTEN = 1
EXIT_USAGE = 2
EXIT_STRICT_SKIPS = 3


def build_parser() -> argparse.ArgumentParser:
    defaults = PrepConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-prep", formatter_class=HelpFormatter,
        description="Turn Embody 3D dyadic captures into HDF5 shards: `sarah-prep raw/ shards/`. "
                    "Bad sequences are reported (terminal and shards/report.json) and skipped.")
    parser.add_argument("paths", nargs="+", type=Path,
                        help="input folders (a section with dataset.json, or its parent) then the output folder; "
                             "with --verify/--info, the shards folder")
    parser.add_argument("--verify", action="store_true", help="check a shards folder (checksums, schema, manifest)")
    parser.add_argument("--info", action="store_true", help="print a summary table of a shards folder")
    parser.add_argument("--audit", action="store_true",
                        help="report what the raw input folders hold, per section (tracked fraction, "
                             "NaN/inf in tracked and untracked frames, audio lengths, dtypes, a warning "
                             "when the tracking mask looks inverted); writes nothing")
    parser.add_argument("--body-model", default=None,
                        help="SMPL-X .npz (or the procedural one); default: the one file under "
                             "<input>/body_models/, else $SARAH_BODY_MODEL")
    parser.add_argument("-j", "--jobs", type=int, default=os.cpu_count() or 1,
                        help="parallel tasks: this process plus N - 1 spawned workers")
    parser.add_argument("--executor", choices=("process", "ray"), default="process",
                        help="where per-sequence work runs: local processes, or Ray")
    parser.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local instance)")
    parser.add_argument("--extractors", default=",".join(defaults.extractors),
                        help="comma-separated audio feature extractors (logmel, hubert-large)")
    parser.add_argument("--hubert-weights", default=defaults.hubert_weights,
                        help="local HuBERT weights for the hubert-large extractor: torchaudio's .pth, "
                             "fairseq's .pt, or a Hugging Face model folder")
    parser.add_argument("--hubert-architecture", choices=("large", "base"),
                        default=defaults.hubert_architecture,
                        help="HuBERT size of those weights (the paper: large)")
    parser.add_argument("--shell-points", type=int, default=defaults.shell_points, help="mesh-shell points per frame")
    parser.add_argument("--split-seed", type=int, default=defaults.split_seed, help="seed of the session split")
    parser.add_argument("--max-shard-mb", type=float, default=defaults.max_shard_bytes / 2**20,
                        help="a shard file closes once it holds about this many MiB")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    parser.add_argument("--sections", default=None,
                        help="comma list of section folder names to prepare (e.g. aiagent); default: all found")
    parser.add_argument("--strict", action="store_true", help="exit non-zero when any input was skipped")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _error(message: str) -> int:
    print(f"sarah-prep: error: {message}", file=sys.stderr)
    return EXIT_USAGE


def _audit(args) -> int:
    from sarah_data.audit import audit, format_audit
    from sarah_data.prep import PrepError, find_sections

    missing = [str(p) for p in args.paths if not p.is_dir()]
    if missing:
        return _error(f"{', '.join(missing)}: no such input folder")
    try:
        sections = find_sections(list(args.paths), [n.strip() for n in args.sections.split(",")
                                                    if n.strip()] if args.sections else None)
    except PrepError as error:
        return _error(str(error))
    results = audit(sections, log=lambda line: None if args.no_progress else print(line, file=sys.stderr))
    print(format_audit(results))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verify or args.info:
        missing = [str(p) for p in args.paths if not p.is_dir()]
        if missing:
            return _error(f"{', '.join(missing)}: no such shards folder")
        return _inspect(args)
    if args.audit:
        return _audit(args)
    if len(args.paths) < 2:
        return _error("give the input folder(s) and then the output folder")
    out = args.paths[-1]
    if out.exists() and not out.is_dir():
        return _error(f"{out}: the output must be a folder, this is a file")
    missing = [str(p) for p in args.paths[:-1] if not p.exists()]
    if missing:
        return _error(f"{', '.join(missing)}: no such input folder")
    if args.jobs < 1:
        return _error(f"-j/--jobs must be at least 1, got {args.jobs}")
    from sarah_data.atomic import OutOfSpace, out_of_space
    from sarah_data.prep import PrepError, prepare

    device = args.device
    if device is None:
        import torch
        device = "cuda" if torch.cuda.is_available() else "cpu"
    config = PrepConfig(extractors=tuple(e.strip() for e in args.extractors.split(",") if e.strip()),
                        hubert_weights=args.hubert_weights, hubert_architecture=args.hubert_architecture,
                        shell_points=args.shell_points,
                        split_seed=args.split_seed, max_shard_bytes=int(args.max_shard_mb * 2**20),
                        device=device)
    problems = config.problems()
    if problems:
        return _error(problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
    try:
        result = prepare(args.paths[:-1], args.paths[-1], config, body_model=args.body_model,
                         jobs=args.jobs, executor=args.executor, ray_address=args.ray_address,
                         progress=not args.no_progress,
                         sections=[n.strip() for n in args.sections.split(",") if n.strip()]
                         if args.sections else None)
    except PrepError as error:
        print(f"sarah-prep: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except (OutOfSpace, OSError, RuntimeError) as error:  # a task's full disk, or the shards'/manifest's
        if not (isinstance(error, OutOfSpace) or out_of_space(error)):
            raise
        where = error if isinstance(error, OutOfSpace) else f"{args.paths[-1]}: no space left on the device"
        print(f"sarah-prep: error: {where}; free some and run the same command again (finished sequences "
              "are kept and reused)", file=sys.stderr)
        return 1
    hours = ", ".join(f"{name} {h:.2f} h" for name, h in result.hours.items())
    rate = result.dyad_seconds / max(result.wall_seconds, 1e-9)
    print(f"sarah-prep: wrote {len(result.written)} sequences ({hours}) in {len(result.shards)} shard files "
          f"to {args.paths[-1]}; left out {len(result.skipped)} (see report.json); "
          f"{result.wall_seconds:.1f} s, {rate:.0f}x real time")
    if not result.written:
        return EXIT_NOTHING_WRITTEN
    if args.strict and result.skipped:
        return EXIT_STRICT_SKIPS
    return 0


def _inspect(args) -> int:
    from sarah_data.verify import format_summary, summarize, verify_shards

    status = 0
    for folder in args.paths:
        if args.verify:
            problems = verify_shards(folder, body_model=args.body_model)
            for problem in problems:
                print(f"{folder}: {problem}")
            print(f"{folder}: {'OK' if not problems else f'{len(problems)} problem(s)'}")
            status = status or (1 if problems else 0)
        if args.info:
            print(format_summary(summarize(folder)))
    return status


if __name__ == "__main__":
    sys.exit(main())
