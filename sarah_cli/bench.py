"""sarah-bench: prep, loader, offline and streaming speed against naive references, one run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_cli.arguments import HelpFormatter, non_negative_int, positive_int


def build_parser() -> argparse.ArgumentParser:
    from sarah_bench.config import BenchConfig
    from sarah_models.accel import DECODER_PRECISIONS, MODE_HELP, MODES

    defaults = BenchConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-bench", formatter_class=HelpFormatter,
        description="Measure prep real-time factor, loader throughput, offline and streaming "
                    "generation (paper and tiny sizes, random weights) and HuBERT-Large "
                    "streaming cost, each against a naive reference in the same run; print a "
                    "table (and JSON with --json). Takes a few minutes; --quick is a smoke run.")
    parser.add_argument("--threads", type=positive_int, default=defaults.threads,
                        help="torch intra-op threads for the whole run (default: automatic, "
                             "every core other processes leave free, re-measured as it runs)")
    parser.add_argument("--background-load", type=non_negative_int,
                        default=defaults.background_load, metavar="N",
                        help="also measure every timed generation figure with N busy processes "
                             "of the bench's own beside it (ended by the bench), side by side "
                             "with the idle figures; with --serve, every level and the soak run "
                             "beside them")
    parser.add_argument("--rounds", type=non_negative_int, default=defaults.rounds, metavar="N",
                        help="with --background-load: stream N more times, idle then loaded in "
                             "each round, and report every streaming figure's median and range "
                             "(one run's figures move with the host's other tenants)")
    parser.add_argument("--mode", choices=MODES, default=defaults.mode,
                        help="optimization of the fast path: "
                             + "; ".join(f"{m}: {h}" for m, h in MODE_HELP.items()))
    parser.add_argument("--decoder", choices=DECODER_PRECISIONS, default=defaults.decoder,
                        help="the VAE decoder's Linears in the int8 and bf16 modes: auto = fp32; "
                             "bf16 is a little faster but moved a trained model's joints by "
                             "centimetres (docs/performance.md)")
    parser.add_argument("--sizes", default=",".join(defaults.sizes),
                        help="model sizes to benchmark (paper, tiny; with --serve also "
                             "fixture-tiny, the shipped trained model with its decoding chain)")
    parser.add_argument("--stream-frames", type=positive_int, default=defaults.stream_frames,
                        metavar="N",
                        help="frames each timed stream generates (a multiple of 4; each stream "
                             "also stops after a minute): p99 chunk latency gets a closed 95 %% "
                             "interval from 1,472 frames (368 chunks) on")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: tiny model, short streams, small prep, no HuBERT")
    parser.add_argument("--no-prep", action="store_true", help="skip the prep benchmark")
    parser.add_argument("--no-loader", action="store_true", help="skip the loader benchmark")
    parser.add_argument("--no-hubert", action="store_true", help="skip HuBERT-Large")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--history", type=Path, default=None,
                        help="append one row to the history table of this markdown file "
                             "(docs/performance.md)")
    serve = parser.add_argument_group("the live server (--serve runs this benchmark alone)")
    serve.add_argument("--serve", action="store_true",
                       help="sarah-serve under load instead: concurrent sessions holding real time "
                            "per size, then a soak of the largest tiny count (about 15 minutes)")
    serve.add_argument("--serve-seconds", type=float, default=15.0, help="seconds per session count")
    serve.add_argument("--soak-seconds", type=float, default=600.0, help="soak length (0: none)")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="keep fixtures and shards here (default: a temporary folder, removed)")
    return parser


def serve_main(args) -> int:
    from dataclasses import asdict

    from sarah_bench.report import write_json
    from sarah_bench.serve import SIZES, ServeBenchConfig, format_serve_report, run_serve_bench

    sizes = tuple(s.strip() for s in args.sizes.split(",") if s.strip())
    if args.serve_seconds <= 0 or args.soak_seconds < 0 or not set(sizes) <= set(SIZES):
        print("sarah-bench: error: --serve needs --serve-seconds > 0, --soak-seconds >= 0 and "
              f"sizes from {', '.join(SIZES)}", file=sys.stderr)
        return 2
    config = ServeBenchConfig(sizes=sizes, level_seconds=args.serve_seconds,
                              soak_seconds=args.soak_seconds, mode=args.mode, threads=args.threads,
                              background_load=args.background_load)
    result = run_serve_bench(config, log=lambda line: print(f"sarah-bench: {line}", file=sys.stderr, flush=True))
    print(format_serve_report(result))
    if args.json is not None:
        write_json(args.json, asdict(result))
        print(f"wrote {args.json}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.serve:
        return serve_main(args)
    from sarah_bench.bench import run_bench
    from sarah_bench.config import BenchConfig
    from sarah_bench.report import append_history, format_report, history_row, write_json

    overrides = {"threads": args.threads, "mode": args.mode, "decoder": args.decoder,
                 "background_load": args.background_load, "rounds": args.rounds}
    if args.sizes != ",".join(BenchConfig().sizes) or not args.quick:
        overrides["sizes"] = tuple(s.strip() for s in args.sizes.split(",") if s.strip())
    if args.stream_frames != BenchConfig().stream_frames:
        overrides["stream_frames"] = args.stream_frames
    if args.no_prep:
        overrides["prep"] = False
    if args.no_loader:
        overrides["loader"] = False
    if args.no_hubert:
        overrides["hubert"] = False
    try:
        config = BenchConfig.quick(**overrides) if args.quick else BenchConfig(**overrides)
    except ValueError as error:
        print(f"sarah-bench: error: {error}", file=sys.stderr)
        return 2
    results = run_bench(config, workdir=args.workdir,
                        log=lambda line: print(f"sarah-bench: {line}", file=sys.stderr, flush=True))
    print(format_report(results))
    if args.json is not None:
        write_json(args.json, results)
        print(f"wrote {args.json}")
    if args.history is not None:
        append_history(args.history, history_row(results))
        print(f"appended a row to {args.history}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
