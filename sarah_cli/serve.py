"""sarah-serve: stream a trained run's agent over WebSocket (docs/protocol.md), with a browser
page at http://HOST:PORT/; or, with --client, stream files through a running server."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from sarah_models.accel import MODE_HELP, MODES
from sarah_cli.arguments import (GUIDANCE_INTERVAL_HELP, IMPUTATION_HELP, NOISE_SCALE_HELP,
                                 SOLVER_HELP, HelpFormatter, add_model_arguments, guide_help,
                                 guidance_interval, guided_modalities, noise_scale, positive_int,
                                 sampling_of)

EXIT_ERROR = 2


def build_parser() -> argparse.ArgumentParser:
    from sarah_models.config import IMPUTATIONS, SOLVERS, StreamConfig
    from sarah_models.serving.server import ServeConfig

    d, s = StreamConfig(), ServeConfig()
    parser = argparse.ArgumentParser(
        prog="sarah-serve", formatter_class=HelpFormatter,
        description="Serve a trained run: each WebSocket connection is one streaming session "
                    "(protocol: docs/protocol.md); http://HOST:PORT/ is a browser page that "
                    "drives it. With --client URL, stream --user-trajectory, --agent-audio and "
                    "--user-audio through a running server and write motion.npz to --out.")
    add_model_arguments(parser, required=False,
                        run_help="training run folder (flow.pt or model.safetensors), or a model "
                                 "file")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="checkpoint or model file (default: RUN/model.safetensors, else RUN/flow.pt)")
    parser.add_argument("--host", default=s.host, help="address to bind; anything but loopback "
                        "needs --public")
    parser.add_argument("--public", action="store_true",
                        help="allow binding a non-loopback address (anyone who reaches it can use the model)")
    parser.add_argument("--port", type=int, default=s.port, help="TCP port (0: any free port)")
    parser.add_argument("--max-sessions", type=int, default=s.max_sessions,
                        help="concurrent sessions; more are refused with close code 1013")
    parser.add_argument("--workers", type=int, default=s.workers, help="compute threads")
    parser.add_argument("--threads", type=positive_int, default=s.threads,
                        help="CPU intra-op threads of each compute thread (default: automatic, "
                             "every core other processes leave free, re-measured as it serves)")
    parser.add_argument("--send-timeout", type=float, default=s.send_timeout,
                        help="seconds a send may wait on a client that does not read before it is closed")
    parser.add_argument("--gather-ms", type=float, default=s.gather_ms,
                        help="chunks are generated in rounds, all waiting sessions' at once: how long "
                             "a round on an idle server waits for the other open sessions' chunks "
                             "(0: start at once)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    parser.add_argument("--speed", choices=MODES, default="fp32",
                        help="inference fast path: " + "; ".join(f"{k}: {v}" for k, v in MODE_HELP.items()))
    parser.add_argument("--body-model", type=Path, default=None,
                        help="a SMPL-X .npz: the live agent is this model's body with zero "
                             "betas (every session's motion on its bones), and sessions that "
                             "open with smplx: true also get its SMPL-X parameters per frame")
    parser.add_argument("--imputation", choices=IMPUTATIONS, default=d.imputation,
                        help=IMPUTATION_HELP + " (every session's)")
    parser.add_argument("--guide", type=guided_modalities, default="all",
                        help=guide_help() + " (every session's)")
    parser.add_argument("--guidance-interval", type=guidance_interval, default="0,1",
                        help=GUIDANCE_INTERVAL_HELP + " (every session's)")
    parser.add_argument("--solver", choices=SOLVERS, default=d.solver,
                        help=SOLVER_HELP + " (every session's)")
    parser.add_argument("--steps", type=int, default=d.steps, help="default solver steps per chunk")
    parser.add_argument("--cfg", type=float, default=d.cfg_scale, help="default guidance scale w")
    parser.add_argument("--noise-scale", type=noise_scale, default=d.noise_scale,
                        help=NOISE_SCALE_HELP + " (every session's)")
    client = parser.add_argument_group("client (--client URL)")
    client.add_argument("--client", metavar="URL", default=None,
                        help="stream files through the server at URL (ws://127.0.0.1:8765) instead of serving")
    client.add_argument("--user-trajectory", type=Path, help="(T, 2) floor x, z at 30 fps (.npy or .csv)")
    client.add_argument("--agent-audio", type=Path, help="agent's audio file")
    client.add_argument("--user-audio", type=Path, help="user's audio file")
    client.add_argument("--gaze", default=str(d.gaze), help="target gaze score, or 'none'")
    client.add_argument("--seed", type=int, default=d.seed, help="noise seed of the session")
    client.add_argument("--chunk-frames", type=int, default=4, help="frames per chunk (a multiple of 4)")
    client.add_argument("--out", type=Path, help="output folder for motion.npz")
    return parser


def _client(args, parser) -> int:
    from sarah_cli.generate import _gaze
    from sarah_data.loading import DataProblem
    from sarah_models.generation.inputs import GenerateError
    from sarah_models.serving.client import ServerError, stream_files

    missing = [flag for flag, value in (("--user-trajectory", args.user_trajectory),
                                        ("--agent-audio", args.agent_audio),
                                        ("--user-audio", args.user_audio), ("--out", args.out)) if value is None]
    if missing:
        parser.error(f"--client needs {', '.join(missing)}")
    try:
        gaze = _gaze(args.gaze)
    except argparse.ArgumentTypeError as error:
        parser.error(str(error))
    try:
        stream_files(args.client, args.user_trajectory, args.agent_audio, args.user_audio, args.out,
                     gaze=gaze, steps=args.steps, seed=args.seed, cfg_scale=args.cfg,
                     chunk_frames=args.chunk_frames)
    except (ServerError, GenerateError, DataProblem) as error:
        print(f"sarah-serve: error: {error}", file=sys.stderr)
        return EXIT_ERROR
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.client is not None:
        return _client(args, parser)
    from sarah_models.config import StreamConfig
    from sarah_models.generation.inputs import GenerateError
    from sarah_models.serving.server import LiveServer, ServeConfig, is_loopback, load_server_models

    if args.run is None:
        parser.error("--run or --pretrained is required to serve (or --client URL to stream files)")
    if not is_loopback(args.host) and not args.public:
        parser.error(f"--host {args.host} is not a loopback address; add --public to serve other machines")
    for flag, value, low in (("--port", args.port, 0), ("--max-sessions", args.max_sessions, 1),
                             ("--workers", args.workers, 1), ("--steps", args.steps, 1)):
        if value < low or (flag == "--port" and value > 65535):
            parser.error(f"{flag} {value} is out of range")
    if args.device is not None:
        from sarah_data.config import device_problems

        for problem in device_problems(args.device):
            parser.error(problem)
    if args.send_timeout <= 0:
        parser.error(f"--send-timeout must be positive, got {args.send_timeout}")
    if not 0 <= args.gather_ms <= 1000:
        parser.error(f"--gather-ms must be between 0 and 1000, got {args.gather_ms}")
    import torch

    # This thread runs the event loop; chunks are computed on the executor's threads. Once this
    # thread had run a 2-thread kernel, the executor's 2-thread chunks took ~1.6x longer on the
    # 2-core VMs (paper size, p50 57-70 -> 100-108 ms; docs/performance.md), so it keeps one.
    torch.set_num_threads(1)
    try:
        # Server-wide sampling flags, and the defaults of what an open message may set.
        defaults = sampling_of(args, StreamConfig())
        models, path = load_server_models(args.run, args.checkpoint, args.device, args.speed, defaults)
    except (GenerateError, ValueError) as error:
        print(f"sarah-serve: error: {error}", file=sys.stderr)
        return EXIT_ERROR
    body = None
    if args.body_model is not None:
        from sarah_data.export import ExportError
        from sarah_data.export.motion import neutral_shape

        try:
            body = neutral_shape(args.body_model, "sarah-serve --body-model")
        except ExportError as error:
            print(f"sarah-serve: error: --body-model {error}", file=sys.stderr)
            return EXIT_ERROR
    config = ServeConfig(host=args.host, port=args.port, max_sessions=args.max_sessions,
                         workers=args.workers, send_timeout=args.send_timeout,
                         threads=args.threads, gather_ms=args.gather_ms)
    server = LiveServer(models, config, defaults, body=body)
    if not is_loopback(args.host):
        print(f"sarah-serve: warning: serving on {args.host}, reachable from other machines",
              file=sys.stderr)

    async def run() -> None:
        ready = asyncio.get_running_loop().create_future()
        task = asyncio.create_task(server.serve(ready))
        port = await ready
        host = f"[{args.host}]" if ":" in args.host else args.host
        threads = "" if server.threads is None else f", threads {server.threads.describe()}"
        print(f"sarah-serve: {path} (step {models.step}, {args.speed}{threads}) on http://{host}:{port}/ "
              f"(WebSocket ws://{host}:{port}/, protocol v1: docs/protocol.md); Ctrl-C stops",
              flush=True)
        await task

    try:
        asyncio.run(run())
    except KeyboardInterrupt:
        print("sarah-serve: stopped", file=sys.stderr)
    except OSError as error:
        print(f"sarah-serve: error: cannot listen on {args.host}:{args.port} ({error})", file=sys.stderr)
        return EXIT_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
