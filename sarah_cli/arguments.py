"""Argument types the commands share: each rejects bad text with one line naming what it wants."""

from __future__ import annotations

import argparse
from pathlib import Path


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def history_tokens(text: str) -> int | str | None:
    """--history: latents of history a stream keeps, 'all' (None: never drop any) or 'window'
    (what one layer of the flow attends to beside the new token: config.HISTORY_WINDOW)."""
    from sarah_models.config import HISTORY_WINDOW

    word = text.strip().lower()
    if word in ("all", "none"):
        return None
    if word == HISTORY_WINDOW:
        return HISTORY_WINDOW
    try:
        return non_negative_int(text)
    except argparse.ArgumentTypeError as error:
        raise argparse.ArgumentTypeError(f"{error} (or 'all', or '{HISTORY_WINDOW}')") from None


HISTORY_HELP = ("latents of history a stream keeps beside the new one: a number, 'all', or "
                "'window': what one layer of the flow attends to (16 for a flow trained with a "
                "17-token window; the paper's 2 for one without a window or the tiny preset's)")


def guided_modalities(text: str) -> tuple[str, ...]:
    """--guide: the modalities the unconditional pass drops, comma-separated, or 'all'."""
    from sarah_models.config import StreamConfig
    from sarah_models.nn.flow import MODALITIES

    if text.strip().lower() == "all":
        return MODALITIES
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"no modalities given; give 'all' or some of "
                                         f"{', '.join(MODALITIES)}")
    try:
        StreamConfig(guide=names)  # the config owns which names are modalities
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{error}, or 'all'") from None
    return names


def guide_help() -> str:
    """--guide's help, naming the modalities the flow has."""
    from sarah_models.nn.flow import MODALITIES

    return ("modalities the unconditional pass of guidance drops, comma-separated: all (the "
            f"paper: w guides the conditioning as a whole) or some of {', '.join(MODALITIES)} "
            "(gaze alone guides only gaze control, a no-op for --gaze none)")


def guidance_interval(text: str) -> tuple[float, float]:
    """--guidance-interval LO,HI: the flow times at which guidance applies."""
    from sarah_models.config import StreamConfig

    try:
        lo, hi = (float(part) for part in text.split(","))
        StreamConfig(guidance_interval=(lo, hi))  # the config owns the rule
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected LO,HI with 0 <= LO < HI <= 1, got {text!r}"
                                         ) from exc
    return lo, hi


GUIDANCE_INTERVAL_HELP = ("LO,HI: guide only the network evaluations at flow times LO <= tau < "
                          "HI (0 noise, 1 data); the others take the conditional prediction. "
                          "0,1 guides every evaluation, as the paper")


def noise_scale(text: str) -> float:
    """--noise-scale: the temperature of each token's starting noise, a finite number above 0."""
    from sarah_models.config import check_noise_scale

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    try:
        check_noise_scale(value)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return value


NOISE_SCALE_HELP = ("temperature of each token's starting noise: 1 is the paper's N(0, I); "
                    "below 1 samples nearer the flow's mode (calmer, less varied motion)")
SOLVER_HELP = "ODE solver (midpoint, the paper's: 2 network evaluations per step; euler: 1)"
IMPUTATION_HELP = ("a stream's history tokens while the new one is solved: final = re-noised "
                   "from their final latents (eq. 4, the paper); trajectory = the states each "
                   "passed through when it was solved, so the stream equals the offline solve "
                   "(docs/models.md)")


def positive_int(text: str) -> int:
    value = non_negative_int(text)
    if value == 0:
        raise argparse.ArgumentTypeError("must be >= 1, got 0")
    return value


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default once: not when its help already says it, and not when there is
    none to show (None, False)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "(default" in text or action.default is None or action.default is False \
                or action.default is argparse.SUPPRESS:
            return text
        return super()._get_help_string(action)


def pretrained_model(name: str) -> Path:
    """A shipped model's checked file (``sarah_models.pretrained``), by name."""
    from sarah_models.pretrained import model_path

    try:
        return model_path(name)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def model_or_name(text: str) -> Path:
    """A path, or the name of a shipped model when no such path exists."""
    from sarah_models.pretrained import MODELS

    return pretrained_model(text) if text in MODELS and not Path(text).exists() else Path(text)


def add_model_arguments(parser: argparse.ArgumentParser, required: bool, run_help: str) -> None:
    """``--run`` (a run folder or a model file) or ``--pretrained NAME``; both land in ``run``."""
    from sarah_models.pretrained import MODELS

    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument("--run", type=Path, default=None, help=run_help)
    group.add_argument("--pretrained", dest="run", type=pretrained_model, metavar="NAME",
                       help="a model shipped with the package instead of --run: "
                            + "; ".join(m.describe() for m in MODELS.values()))


def add_sampling_arguments(parser: argparse.ArgumentParser, defaults,
                           steps_help: str = "solver steps",
                           imputation_help: str = IMPUTATION_HELP) -> None:
    """The sampling flags of sarah-eval, sarah-generate and the scripts that sample as an
    evaluation does: --steps, --solver, --cfg, --noise-scale, --guide, --guidance-interval
    and --imputation, defaults from ``defaults`` (an ``EvalConfig`` or ``StreamConfig``);
    ``sampling_of`` reads them back."""
    from sarah_models.config import IMPUTATIONS, SOLVERS

    parser.add_argument("--steps", type=int, default=defaults.steps, help=steps_help)
    parser.add_argument("--solver", choices=SOLVERS, default=defaults.solver, help=SOLVER_HELP)
    parser.add_argument("--cfg", type=float, default=defaults.cfg_scale, help="guidance scale w")
    parser.add_argument("--noise-scale", type=noise_scale, default=defaults.noise_scale,
                        help=NOISE_SCALE_HELP)
    parser.add_argument("--guide", type=guided_modalities, default="all", help=guide_help())
    parser.add_argument("--guidance-interval", type=guidance_interval, default="0,1",
                        help=GUIDANCE_INTERVAL_HELP)
    parser.add_argument("--imputation", choices=IMPUTATIONS, default=defaults.imputation,
                        help=imputation_help)


def sampling_of(args: argparse.Namespace, config):
    """``config`` (an ``EvalConfig`` or ``StreamConfig``) with the flags of
    ``add_sampling_arguments`` set; ValueError as the config's own checks raise it."""
    from dataclasses import replace

    return replace(config, steps=args.steps, solver=args.solver, cfg_scale=args.cfg,
                   noise_scale=args.noise_scale, guide=args.guide,
                   guidance_interval=args.guidance_interval, imputation=args.imputation)
