"""sarah-train: train the causal VAE, then the flow matcher on its frozen latents.

Multi-GPU: ``torchrun --nproc_per_node 8 -m sarah_cli.train --stage all --shards shards/ --out runs/x``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_models.config import PRESETS, RunConfig, decoding_settings, preset_values
from sarah_cli.arguments import HelpFormatter, model_or_name

EXIT_ERROR = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sarah-train", formatter_class=HelpFormatter,
        description="Staged training of SARAH's motion models: `vae` (causal VAE), then `flow` "
                    "(causal flow matcher on the frozen VAE's latents), or `all` for both. "
                    "Writes OUT/config.json, OUT/vae.pt, OUT/flow.pt, *_log.jsonl and *_loss.png. "
                    "Under torchrun (WORLD_SIZE > 1) every process trains on its own data slice "
                    "(DDP; nccl on CUDA, gloo on CPU) and rank 0 writes the files.",
        epilog="config fields for --set, with the paper preset's value (|the tiny preset's where "
               "it differs): " + " ".join(preset_values()))
    parser.add_argument("--stage", choices=("vae", "flow", "all", "model"), default="all",
                        help="what to train; flow needs OUT/vae.pt; model trains nothing: it "
                             "writes OUT/model.safetensors from --init-from's weights with the "
                             f"decoding settings given by --set ({', '.join(decoding_settings())}; "
                             "with --shards, the skeleton of their training split when the "
                             "model has none)")
    parser.add_argument("--config", choices=PRESETS, default="paper",
                        help="model and training preset: paper sizes, or tiny for CPU runs")
    parser.add_argument("--shards", type=Path, default=None,
                        help="shards folder written by sarah-prep (with stats.h5); every stage "
                             "but model needs it (model: the skeleton of their training split, "
                             "for a model that has none)")
    parser.add_argument("--out", type=Path, required=True, help="run folder, e.g. runs/NAME")
    parser.add_argument("--resume", action="store_true",
                        help="continue from OUT/<stage>.pt (exactly: same data order and noise)")
    parser.add_argument("--replace-changed", action="store_true",
                        help="with --resume: a stage whose checkpoint in OUT was trained with "
                             "another config (say, after an upgrade changed a preset) is moved "
                             "to OUT/replaced-<time>/ and trained afresh, its flow too when the "
                             "VAE changed; nothing is deleted (make demo uses it)")
    parser.add_argument("--init-from", type=model_or_name, default=None, metavar="CKPT",
                        help="fine-tune: start each trained stage from the weights of CKPT (a "
                             "checkpoint, a run folder with vae.pt / flow.pt, a model file such as "
                             "model.safetensors, or a shipped model's name such as fixture-tiny) "
                             "with a fresh "
                             "step count, optimizer and LR schedule; loss weights (e.g. --set "
                             "vae.velocity_weight=100) and train.lr_schedule may differ, sizes "
                             "may not; --stage flow into a folder without vae.pt fine-tunes "
                             "CKPT's flow on CKPT's own VAE")
    parser.add_argument("--decoding-from", type=model_or_name, default=None, metavar="MODEL",
                        help="with --stage model: start from the decoding settings MODEL was "
                             "written with (a model file, flow checkpoint or run folder, or a "
                             "shipped model's name such as fixture-tiny); --set changes them "
                             "further")
    parser.add_argument("--decoder-from", type=model_or_name, default=None, metavar="CKPT",
                        help="with --stage model: the VAE of CKPT (a run folder with vae.pt, a "
                             "checkpoint or a model file) in place of --init-from's: a decoder "
                             "stage trained from --init-from's VAE with --set "
                             "train.freeze_encoder=true reads the latents its flow learned, so "
                             "the flow needs no training; refused unless its encoder and motion "
                             "statistics are the model's")
    parser.add_argument("--device", default=None,
                        help="cpu, cuda or cuda:N; None = cuda when available (cuda:LOCAL_RANK "
                             "under torchrun), else cpu")
    parser.add_argument("--steps", type=int, default=None,
                        help="total steps of each stage trained; None = the preset's "
                             "train.vae_steps / train.flow_steps")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="windows per process per step; None = the preset's train.batch_size")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of data order and noise; None = the preset's train.seed")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="FIELD=VALUE",
                        help="override a config field, e.g. --set train.lr=3e-4 --set "
                             "vae.hidden=512 --set train.audio_features=logmel (repeatable; "
                             "sections vae, flow, train; --stage flow trains on OUT/vae.pt "
                             "and takes only its decoding settings from --set vae.*)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def run_config(args: argparse.Namespace) -> RunConfig:
    overrides = list(args.overrides)
    if args.batch_size is not None:
        overrides.append(f"train.batch_size={args.batch_size}")
    if args.seed is not None:
        overrides.append(f"train.seed={args.seed}")
    if args.steps is not None:
        overrides += [f"train.vae_steps={args.steps}", f"train.flow_steps={args.steps}"]
    return RunConfig.preset(args.config).with_overrides(overrides)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.replace_changed and not args.resume:
        parser.error("--replace-changed goes with --resume (it decides what a resume keeps)")
    if args.decoding_from is not None and args.stage != "model":
        parser.error("--decoding-from goes with --stage model (a trained stage writes its "
                     "decoding settings from --set)")
    if args.decoder_from is not None and args.stage != "model":
        parser.error("--decoder-from goes with --stage model (it writes a model file)")
    if args.stage == "model":
        return write_model(args)
    if args.shards is None:
        parser.error(f"--stage {args.stage} needs --shards")
    try:
        config = run_config(args)
    except ValueError as exc:
        print(f"sarah-train: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    if args.device is not None:
        from sarah_data.config import device_problems

        for problem in device_problems(args.device):
            print(f"sarah-train: error: {problem}", file=sys.stderr)
            return EXIT_ERROR
    import torch

    if args.config == "paper" and (args.device or ("cuda" if torch.cuda.is_available() else "cpu")) == "cpu":
        print("sarah-train: note: training the paper-size model on a CPU (many seconds per step); "
              "--config tiny is the preset for CPUs", file=sys.stderr)
    from sarah_data.loading import DataProblem
    from sarah_models.training.distributed import cleanup_distributed, is_main_process
    from sarah_models.training.model_file import MODEL_FILE, write_model_file
    from sarah_models.training.stages import train

    stages = ("vae", "flow") if args.stage == "all" else (args.stage,)
    vae_settings = {name for section, name in map(config.target_of, args.overrides)
                    if section == "vae"}
    try:
        if args.replace_changed and is_main_process():
            from sarah_models.training.stages import set_aside, stale_stages

            stale = stale_stages(Path(args.out), config, stages)
            aside = set_aside(Path(args.out), stale)
            if aside is not None:
                print(f"sarah-train: {', '.join(stale)} of {args.out} had another config: "
                      f"moved to {aside}, training afresh", file=sys.stderr)
        for stage in stages:
            path = train(stage, config, args.shards, args.out, resume=args.resume,
                         device=args.device, init_from=args.init_from,
                         vae_settings=vae_settings, progress=not args.no_progress)
            print(f"{stage}: checkpoint {path}")
            if stage == "flow" and is_main_process():
                model = write_model_file(path, Path(args.out) / MODEL_FILE)
                print(f"model file (for sarah-generate and sharing; loads without pickle): {model}")
    except (DataProblem, ValueError, FileNotFoundError, FileExistsError, KeyError, OSError) as exc:
        print(f"sarah-train: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        cleanup_distributed()
    return 0


def write_model(args: argparse.Namespace) -> int:
    """--stage model: a model file from another run's weights, with other decoding settings."""
    from sarah_data.loading import DataProblem
    from sarah_models.training.model_file import (MODEL_FILE, decoding_of, flow_source,
                                                  write_model_file)

    if args.init_from is None:
        print("sarah-train: error: --stage model writes the weights of --init-from (a run folder, "
              "flow.pt or a model file); give it", file=sys.stderr)
        return EXIT_ERROR
    try:
        decoding = [] if args.decoding_from is None else decoding_of(args.decoding_from)
        model = write_model_file(flow_source(args.init_from), Path(args.out) / MODEL_FILE,
                                 decoding + args.overrides, args.shards, args.decoder_from)
    except (DataProblem, ValueError, FileNotFoundError, OSError) as exc:
        print(f"sarah-train: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"model file (for sarah-generate and sharing; loads without pickle): {model}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
