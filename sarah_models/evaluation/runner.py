"""The library behind ``sarah-eval``: the paper's Table 1 and Table 2 on a split's test windows.

Windows (A.2): the split's non-overlapping T = 400-frame windows (``WindowDataset.sliding``:
every tracked run tiled from its start, either person as the agent), in the dataset's order
(sequence, start, agent). When there are more than ``windows`` of them, ``windows`` evenly
spaced ones are kept (indices round(linspace(0, n - 1, windows))), so the subset spans the whole
split; when there are fewer, all are used and the tables say so.

Methods, each producing one (T, Dx) motion per window in its window frame:
  gt      the window's own motion (a reference row: per-clip metrics of real motion; FGD "-")
  random  RandomBaseline: a random training window
  nn      NearestNeighbourBaseline: the nearest of 2048 random training windows (full clip)
  model   the run's flow checkpoint, once per gaze setting: streaming 4 frames at a time by
          default (what users run), or the offline protocol (all T frames denoised at once
          under the causal mask, as the paper times FPS)
  vae     the run's VAE reconstructing the window (opt-in)
  decoded the window's own motion through the run's decoding chain (``sampling.decoding``: seam
          inertia, root hold, rigid skeleton, foot lock, as its VAE config asks; opt-in): the
          chain's own floor, what it does to real motion, which no flow or VAE can get under
  blur    calibration: the window's own motion through a centred moving average (opt-in)
  jitter  calibration: the window's own motion plus i.i.d. noise of a few mm (opt-in)

Speaking: a window is S when the agent's per-frame speaking labels stored in the shards
(``sarah_data.speaking`` on the agent's separated audio energy) satisfy the clip rule
``clip_is_speaking`` with the shards' speaking configuration, NS otherwise.

FPS = T / median seconds to produce one window's motion (the paper: "generating all 400 frames
in one go and then dividing the total time taken by 400"; the median ignores warm-up). R
(real-time) is FPS >= 30, the motion's frame rate; C (causal) is a property of the method.

Every row but GT's is scored on FGD_acc by body part too (``metrics.body_parts``; the shell split
by the first window's first frame), each part's acceleration energy against GT's beside it:
table1.md's last table, and the rows' ``fgd_acc@<part>`` values in table1.json.

Outputs in ``out``: table1.md/.json, table2.md/.json, windows.json (the windows evaluated and
their S/NS flags), plots/metric_<name>.png (bars across methods), plots/gaze_control.png,
plots/paths.png (top views of where each method's agent walks, ``paths.py``) and
plots/fgd_acc_by_part.png (the by-part table as bars, log scale); with the model, latents.md/.json
and plots/latent_directions.png: how the Table 1 row's sampled latents fill the principal
directions of the encoder's latents of the same windows (``latent_directions.py``);
with the "vae" method also reconstruction.md/.json, its error per body part in mm
(``reconstruction.py``).
Memory stays at a few clips: clips are produced lazily while the metrics read them (the model row's
latents are kept whole, a few floats per token: ``latent_directions.py``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from sarah_data.atomic import atomic_write_text
from sarah_data.constants import FPS
from sarah_data.skeleton import MotionLayout, shell_parts

from ..config import (CFG_SCALE, HISTORY_TOKENS, HISTORY_WINDOW, NOISE_SCALE, SOLVER_STEPS,
                      STRIDE, WINDOW, StreamConfig, check_gaze, check_history, check_noise_scale)
from .metrics import (
    FrechetRidgeWarning,
    MetricsConfig,
    clip_values,
    evaluate,
    reference_table,
    registered,
)
from .tables import (
    MethodResult,
    fps_of,
    gaze_label,
    number,
    plot_gaze_control,
    plot_metric_bars,
    plot_parts,
    table1_markdown,
    table2_markdown,
    write_json,
)
from .degradations import BLUR_FRAMES, JITTER_MM, blurred, jittered
from .latent_directions import (LatentRecorder, directions_markdown, pelvis_floor,
                                plot_directions)
from .paths import floor_path_length, pick_windows, plot_paths, recording
from .reconstruction import ReconstructionErrors, summary_markdown
from .windows import MethodClips, TestWindows, gt_clips, select_windows

METHODS = ("gt", "real", "random", "nn", "model", "vae", "decoded", "blur", "jitter")
# Table 1's rows: the paper's four and the real-vs-real floor; "vae" and the calibration rows
# (``degradations``: the ground truth blurred or jittered by a known amount) are opt-in
PAPER_METHODS = ("gt", "real", "random", "nn", "model")
PROTOCOLS = ("offline", "stream")

class EvalError(Exception):
    """A problem with the inputs of an evaluation, stated in one line."""


@dataclass(frozen=True)
class EvalConfig:
    """sarah-eval settings; defaults are the paper's (sec. 4, A.2, A.3)."""

    split: str = "test"
    windows: int = 2048  # test windows evaluated ("2048 sequences in total")
    window: int = WINDOW  # T frames per window
    gaze: tuple[float | None, ...] = (None, 0.0, 0.8, 1.0)  # Table 2 rows; None = no gaze control
    table1_gaze: float | None = None  # the model row of Table 1 (the paper's "Ours" = the ∅ row)
    methods: tuple[str, ...] = PAPER_METHODS
    batch_clips: int = 16  # clips per FGD batch of the Avg column
    seed: int = 0
    steps: int = SOLVER_STEPS  # solver steps
    solver: str = StreamConfig.solver  # the paper's midpoint method, or euler (StreamConfig)
    cfg_scale: float = CFG_SCALE
    noise_scale: float = NOISE_SCALE  # temperature of the model's starting noise (StreamConfig)
    # Streamed latents kept as history (None: all). The offline protocol has none to drop.
    history_tokens: int | str | None = HISTORY_WINDOW
    protocol: str = "stream"  # what users run; "offline" is the paper's fps protocol
    imputation: str = StreamConfig.imputation  # a stream's history ("final": the paper's eq. 4)
    # modalities guidance's unconditional pass drops (StreamConfig.guide; all four: the paper)
    guide: tuple[str, ...] = StreamConfig.guide
    # flow times at which guidance applies (StreamConfig.guidance_interval; (0, 1): the paper)
    guidance_interval: tuple[float, float] = StreamConfig.guidance_interval
    library_size: int = 2048  # NN library and Random pool of training windows
    train_split: str = "train"
    # The shards the Random pool and NN library are drawn from (default: the evaluated ones).
    # Evaluating on a corpus the model never saw, point this at its training shards.
    library_shards: str | None = None
    blur_frames: int = BLUR_FRAMES  # the "blur" row's moving average
    jitter_mm: float = JITTER_MM  # the "jitter" row's noise
    features: str | None = None  # audio extractor when no model is evaluated (else the run's)
    device: str | None = None

    def __post_init__(self) -> None:
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods:
            raise EvalError(f"unknown method(s) {unknown or '(none given)'}; choose from "
                            f"{', '.join(METHODS)}")
        if self.protocol not in PROTOCOLS:
            raise EvalError(f"unknown protocol {self.protocol!r}; choose offline or stream")
        try:
            StreamConfig(guide=tuple(self.guide))
        except ValueError as error:
            raise EvalError(f"--guide: {error}") from None
        try:  # the streams' own rules, one line each
            StreamConfig(solver=self.solver, imputation=self.imputation)
        except ValueError as error:
            raise EvalError(str(error)) from None
        for name in ("windows", "window", "batch_clips", "steps", "library_size", "blur_frames"):
            if getattr(self, name) < 1:
                raise EvalError(f"--{name.replace('_', '-')} must be positive, got "
                                f"{getattr(self, name)}")
        try:
            check_noise_scale(self.noise_scale)
        except ValueError as error:
            raise EvalError(f"--noise-scale: {error}") from None
        if not self.jitter_mm >= 0:
            raise EvalError(f"--jitter-mm must be >= 0, got {self.jitter_mm}")
        try:
            check_history(self.history_tokens)
        except ValueError as error:
            raise EvalError(f"--history: {error}") from None
        for g in (*self.gaze, self.table1_gaze):
            try:
                check_gaze(g)
            except ValueError as error:
                raise EvalError(str(error)) from None

    @property
    def model_gazes(self) -> tuple[float | None, ...]:
        """Every gaze setting the model runs with: the sweep, plus Table 1's if not in it."""
        return tuple(self.gaze) + (() if self.table1_gaze in self.gaze else (self.table1_gaze,))


# --------------------------------------------------------------------------- running


@dataclass
class Evaluation:
    """Everything an evaluation produced."""

    table1: list[MethodResult]
    table2: list[MethodResult]
    num_windows: int
    available_windows: int
    num_speaking: int
    reconstruction: dict | None = None  # the "vae" row's errors per body part (summary, mm)
    latents: dict | None = None  # the Table 1 model row's latent directions (latent_directions.py)
    paths: list[Path] = field(default_factory=list)


def _open_shards(shards_dir: Path, split: str, features: str, window: int):
    from sarah_data.dataset import WindowDataset
    from sarah_data.loading import DataProblem
    from sarah_data.shards import ShardSet

    try:
        shard_set = ShardSet(shards_dir)
    except (DataProblem, OSError, ValueError) as exc:
        raise EvalError(str(exc)) from None
    try:
        if not shard_set.manifest.shards:
            raise EvalError(f"{shards_dir}: the shards folder holds no shard files")
        stored = sorted(shard_set.attrs.extractors)
        speaking = shard_set.manifest.config.get("speaking", {})
    finally:
        shard_set.close()
    if features not in stored:
        raise EvalError(f"{shards_dir}: mismatched feature extractor: {features!r} is needed, "
                        f"the shards hold {stored or 'no features'}")
    try:
        dataset = WindowDataset.sliding(shards_dir, split, extractor=features, window=window)
    except (DataProblem, OSError, ValueError) as exc:
        raise EvalError(str(exc)) from None
    if len(dataset) == 0:
        reasons = "; ".join(f"{name}: {why}" for name, why in dataset.skipped[:3])
        more = f" (+{len(dataset.skipped) - 3} more)" if len(dataset.skipped) > 3 else ""
        raise EvalError(f"{shards_dir}: split {split!r} has no windows of {window} frames with "
                        f"{features!r} audio" + (f" (skipped: {reasons}{more})" if reasons else ""))
    return dataset, speaking


def _training_windows(shards_dir: Path, features: str, config: EvalConfig):
    from sarah_data.dataset import WindowDataset
    from sarah_data.loading import DataProblem

    try:
        return WindowDataset(shards_dir, config.train_split, extractor=features,
                             window=config.window, seed=config.seed, length=config.library_size)
    except (DataProblem, OSError, ValueError) as exc:
        raise EvalError(f"{shards_dir}: training windows for the baselines: {exc}") from None


def window_seed(seed: int, index: int) -> int:
    """The seed of window ``index``'s model row (its noise and detail draws) under ``seed``."""
    return int(np.random.default_rng((seed, index)).integers(2**31 - 1))


def window_generator(models, config: EvalConfig, gaze: float | None):
    """A function (window item, its index) -> the model's ``generation.outputs.Result`` for that
    window, generated as the model's Table 1 row is (``config.protocol``, steps, cfg, seed)."""
    from ..generation.inputs import Inputs
    from ..generation.run import generate
    from ..sampling.stream import IDENTITY

    def run(item: dict, index: int):
        # Windows are already in the window frame: the identity anchor generates in that frame.
        inputs = Inputs(user_head=item["user_head"].numpy(),
                        agent_speaking=item["agent_speaking"].numpy() > 0.5,
                        user_speaking=item["user_speaking"].numpy() > 0.5,
                        anchor=IDENTITY, source={},
                        agent_audio=item["agent_audio"].numpy(),
                        user_audio=item["user_audio"].numpy())
        stream = StreamConfig(steps=config.steps, solver=config.solver,
                              cfg_scale=config.cfg_scale, gaze=gaze,
                              noise_scale=config.noise_scale,
                              history_tokens=config.history_tokens,
                              imputation=config.imputation, guide=config.guide,
                              guidance_interval=config.guidance_interval,
                              seed=window_seed(config.seed, index))
        return generate(models, inputs, stream, offline=config.protocol == "offline")

    return run


def _model_producer(models, config: EvalConfig, gaze: float | None,
                    latents: LatentRecorder | None = None):
    run = window_generator(models, config, gaze)
    if latents is not None:
        return latents.observe(run)
    return lambda item, index: run(item, index).motion


def _encoder_means(models):
    """A window item -> the run's encoder means of its motion, (1, K, Dz) unstandardized."""
    device = next(models.vae.parameters()).device
    nz, vae = models.normalizer, models.vae
    return lambda item: vae.encode(nz.normalize("motion", item["motion"].to(device))[None])[0]


def _encoder_latents(models):
    """A window item -> its (K, Dz) encoder means, standardized as the flow learned them."""
    means = _encoder_means(models)
    return lambda item: models.normalizer.normalize("latent", means(item))[0].float().cpu().numpy()


def _user_floor(item: dict, decoding) -> np.ndarray | None:
    """A window's user floor path (T, 2) in the frame its motion is in (the window frame), where
    ``decoding``'s root hold turns the body by it (``vae.root_hold_turn``); else None."""
    return item["user_head"].double().cpu().numpy() if decoding.reads_user else None


def _vae_producer(models):
    """The run's VAE reconstructing the ground truth (encoder mean, then decoder, decoded the way
    the generators decode: ``sampling.decoding``): the best any flow sample can decode to,
    which separates the VAE's error from the flow's."""
    from ..sampling.decoding import decoder_frames, stream_decoding

    nz, vae, means = models.normalizer, models.vae, _encoder_means(models)

    def produce(item: dict, index: int) -> np.ndarray:
        # a stochastic decoder (vae.detail_dim) draws its detail as a stream seeded by the window does
        frames, stance = decoder_frames(vae, nz, means(item), index)
        decoding = stream_decoding(vae, nz)
        return decoding(frames, stance, _user_floor(item, decoding)).astype(np.float32)

    return produce


def _decoded_producer(models):
    """The ground truth through the run's decoding chain, as a stream's decoded motion goes
    through it: what the chain alone does to real motion."""
    from ..sampling.decoding import stream_decoding

    def produce(item: dict, index: int) -> np.ndarray:
        motion = item["motion"].double().cpu().numpy()
        decoding = stream_decoding(models.vae, models.normalizer)
        return decoding(motion, None, _user_floor(item, decoding)).astype(np.float32)

    return produce


def _load_model(run: Path | None, config: EvalConfig, method: str = "model"):
    """The run's flow-stage models (a folder's model file first: ``load_run``); for "vae" or
    "decoded" alone, a folder's VAE checkpoint will do when it has neither."""
    from ..generation.run import GenerateError, load_run
    from ..training.model_file import MODEL_FILE, flow_source

    if run is None:
        raise EvalError(f"--run is required to evaluate the {method} (or leave {method!r} out "
                        "of --methods)")
    checkpoint = None
    if method in ("vae", "decoded") and run.is_dir() and not flow_source(run).is_file():
        checkpoint = run / "vae.pt"
        if not checkpoint.is_file():
            raise EvalError(f"{run}: no {MODEL_FILE}, flow.pt or vae.pt (train the VAE stage "
                            "first)")
    try:
        models, _ = load_run(run, checkpoint, device=config.device, need_flow=method == "model")
    except GenerateError as exc:
        raise EvalError(str(exc)) from None
    return models


def run_evaluation(run: Path | str | None, shards: Path | str, out: Path | str,
                   config: EvalConfig = EvalConfig(), progress: bool = True,
                   echo: Callable[[str], None] = print) -> Evaluation:
    """Everything ``sarah-eval`` does: windows, methods, metrics, tables, plots."""
    import torch
    from tqdm import tqdm

    from sarah_data.speaking import SpeakingConfig, clip_is_speaking

    shards, out = Path(shards), Path(out)
    run = None if run is None else Path(run)
    models = _load_model(run, config) if "model" in config.methods else None
    if models is not None and config.history_tokens == HISTORY_WINDOW:
        from ..sampling.stream import window_history  # the number the tables state

        config = replace(config, history_tokens=window_history(models.flow))
    vae_models = None
    if "vae" in config.methods or "decoded" in config.methods:
        method = "vae" if "vae" in config.methods else "decoded"
        vae_models = models if models is not None else _load_model(run, config, method)
    loaded = models or vae_models
    features = loaded.features if loaded is not None else (config.features or "logmel")
    if loaded is not None and config.window % loaded.vae.stride:
        raise EvalError(f"--window {config.window} is not a multiple of the model's stride "
                        f"{loaded.vae.stride}")
    dataset, speaking_settings = _open_shards(shards, config.split, features, config.window)
    if loaded is not None and dataset.motion_dim != loaded.dims["motion"]:
        raise EvalError(f"{shards}: motion width {dataset.motion_dim} (shell points) differs "
                        f"from the checkpoint's {loaded.dims['motion']}")
    if models is not None and dataset.audio_dim != models.flow.audio_dim:
        raise EvalError(f"{shards}: mismatched feature extractor: {features!r} features have "
                        f"{dataset.audio_dim} channels, the checkpoint expects "
                        f"{models.flow.audio_dim}")
    indices = select_windows(len(dataset), config.windows)
    windows = TestWindows(dataset, indices)
    try:
        speaking_config = SpeakingConfig(**speaking_settings)
    except TypeError as exc:
        raise EvalError(f"{shards}: unreadable speaking settings in the manifest ({exc})") from None
    speaking, user_travel = np.zeros(len(windows), dtype=bool), np.zeros(len(windows))
    for i in tqdm(range(len(windows)), desc="S/NS labels", unit="window",
                  disable=not progress, leave=False):
        item = windows[i]
        speaking[i] = clip_is_speaking(item["agent_speaking"].numpy() > 0.5, speaking_config)
        user_travel[i] = floor_path_length(item["user_head"].numpy())
    drawn = pick_windows(user_travel)
    layout = MotionLayout.from_width(dataset.motion_dim)
    echo(f"{len(windows)} of {len(dataset)} {config.window}-frame windows of split "
         f"{config.split!r} ({int(speaking.sum())} S, {int((~speaking).sum())} NS), features "
         f"{features!r}")

    # Windows are in their window frame already: re-normalizing to a decoded frame-0 pelvis
    # would rotate a whole clip by that frame's yaw error. Seams are looked for at the run's
    # latent blocks. FGD_acc is scored by body part too, the shell split once, by the first
    # window's first frame, for every method alike.
    icosahedra, shell = layout.split(windows[0]["motion"].numpy()[0])
    metrics_config = MetricsConfig(batch_clips=config.batch_clips, normalize_window=False,
                                   block_frames=loaded.vae.stride if loaded else STRIDE,
                                   shell_parts=shell_parts(icosahedra, shell, layout.joint_names))
    train_windows = None
    if "random" in config.methods or "nn" in config.methods:
        library = shards if config.library_shards is None else Path(config.library_shards)
        train_windows = _training_windows(library, features, config)

    gt_values: dict[str, np.ndarray] | None = None  # the GT row's clip_values, once scored

    def score(key: str, label: str, produce, causal: bool | None, gaze=None,
              reference: bool = False, timed: bool = True, pooled: bool = True,
              draw: bool = True) -> MethodResult:
        nonlocal gt_values
        produce, floor_paths = recording(produce, drawn if draw else (), layout)
        with tqdm(total=len(windows), desc=label, unit="window", disable=not progress,
                  leave=False) as bar:
            clips = MethodClips(windows, produce, bar)
            if reference:  # its per-clip values are every later row's paired comparison
                gt_values = clip_values(clips, metrics_config)
                table = reference_table(clips, speaking, metrics_config, gt_values)
            else:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", FrechetRidgeWarning)
                    table = evaluate(clips, gt_clips(windows), speaking, config=metrics_config,
                                     reference_values=gt_values)
                ridged = [w for w in caught if issubclass(w.category, FrechetRidgeWarning)]
                for w in caught:
                    if not issubclass(w.category, FrechetRidgeWarning):
                        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
                if ridged:
                    echo(f"{label}: {len(ridged)} Fréchet distance(s) needed a covariance ridge "
                         f"(near-singular covariances; see metrics.frechet_distance_from_moments)")
        if not pooled:  # a row whose clips are the ground truth's own, permuted
            for name in table.distances():
                values = table.values[name]
                values.pooled = values.pooled_low = values.pooled_high = math.nan
        fps = fps_of(clips.seconds, config.window) if timed and not reference else None
        result = MethodResult(key, label, causal, fps, table, gaze, reference, floor_paths)
        shown = result.shown()
        echo(f"{label}: " + ", ".join(f"{m.label} {number(shown[f'{m.name}/avg'], m.decimals)}"
                                      for m in registered())
             + ("" if fps is None else f", {fps:.0f} FPS"))
        return result

    table1: list[MethodResult] = []
    if "gt" in config.methods:
        table1.append(score("gt", "GT", lambda item, _: item["motion"], None, reference=True))
    if "real" in config.methods:
        # The floor: real motion of the other half of the windows scored like a method, so
        # every figure has the value two disjoint sets of real clips give.
        half = len(windows) // 2
        # Pooled over all windows, "other windows" are the same set permuted: 0 by design.
        # Not drawn in paths.png: its path is another window's, and the degradations' below are
        # GT's own, nearly unchanged.
        table1.append(score("real", "Real (other windows)",
                            lambda _, i: windows[(i + half) % len(windows)]["motion"], None,
                            timed=False, pooled=False, draw=False))
    if "blur" in config.methods:
        table1.append(score("blur", f"GT, blurred ({config.blur_frames} frames)",
                            lambda item, _: blurred(item["motion"], config.blur_frames), None,
                            timed=False, draw=False))
    if "jitter" in config.methods:
        table1.append(score("jitter", f"GT + {config.jitter_mm:g} mm jitter",
                            lambda item, i: jittered(item["motion"], config.jitter_mm,
                                                     config.seed, i), None, timed=False,
                            draw=False))
    if "random" in config.methods:
        from .baselines import RandomBaseline

        baseline = RandomBaseline(train_windows, seed=config.seed)
        table1.append(score("random", "Random", baseline.motion, False))
    if "nn" in config.methods:
        from .baselines import NearestNeighbourBaseline, NNConfig

        nn = NearestNeighbourBaseline(train_windows, NNConfig(library_size=config.library_size),
                                      seed=config.seed, progress=progress)
        table1.append(score("nn", "NN", nn.motion, False))
    sweep: dict[float | None, MethodResult] = {}
    latent_directions = None
    if models is not None:
        # The Table 1 row's samples against the encoder's latents of the same windows.
        recorder = LatentRecorder(_encoder_latents(models),
                                  pelvis_floor(layout, models.vae.stride))
        with torch.inference_mode():
            for g in config.model_gazes:
                label = f"Model (g = {gaze_label(g)}, {config.protocol})"
                observed = recorder if g == config.table1_gaze else None
                sweep[g] = score(f"model@{gaze_label(g)}", label,
                                 _model_producer(models, config, g, observed), True, gaze=g)
        try:
            latent_directions = recorder.summary()
        except ValueError as error:  # e.g. latents that do not vary: the tables stand without it
            echo(f"Latent directions: not written ({error})")
        if latent_directions is not None:
            lead = latent_directions["bands"][0]
            echo(f"Latent directions: {lead['directions'][1]} of {latent_directions['channels']} "
                 f"directions hold {lead['share']:.0%} of the data's latent variance; there the "
                 f"samples' spread is {lead['spread']:.2f}x the data's, their token-to-token "
                 f"change {lead['change_ratio']:.2f}x")
        table1.append(replace(sweep[config.table1_gaze], key="model",
                              label=f"Model ({config.protocol}, g = "
                                    f"{gaze_label(config.table1_gaze)})"))
    reconstruction = None
    if "vae" in config.methods:
        errors = ReconstructionErrors(MotionLayout.from_width(dataset.motion_dim))
        with torch.inference_mode():
            table1.append(score("vae", "VAE (reconstruction)",
                                errors.observe(_vae_producer(vae_models)), True))
        reconstruction = errors.summary()
        for group, row in reconstruction.items():
            echo(f"VAE reconstruction, {group}: position {row['position']:.1f} mm"
                 + (f", orientation {row['orientation']:.1f} mm" if "orientation" in row else ""))
    if "decoded" in config.methods:
        table1.append(score("decoded", "GT, decoded (the run's chain)",
                            _decoded_producer(vae_models), True, timed=False))
    table2 = [sweep[g] for g in config.gaze] if models is not None else []

    result = Evaluation(table1, table2, len(windows), len(dataset), int(speaking.sum()),
                        reconstruction, latent_directions)
    result.paths = write_outputs(out, result, config, shards, run, features, windows, speaking)
    drawn_rows = [(row.label, row.floor_paths) for row in table1 if row.floor_paths]
    if drawn_rows:
        result.paths.append(plot_paths(out / "plots" / "paths.png",
                                       {i: windows[i]["user_head"].numpy() for i in drawn},
                                       drawn_rows))
    return result


def _caption1(ev: Evaluation, config: EvalConfig, shards: Path) -> str:
    if ev.available_windows > config.windows:
        count = f"{ev.num_windows} of {ev.available_windows} {config.split} windows (evenly spaced)"
    elif ev.available_windows < config.windows:
        count = (f"{ev.num_windows} {config.split} windows (all the split has; {config.windows} "
                 f"requested)")
    else:
        count = f"{ev.num_windows} {config.split} windows"
    scale = ev.table1[0].table.display_scale if ev.table1 else MetricsConfig().display_scale
    return (f"Table 1: comparison on {count} of T = {config.window} frames ({config.window / FPS:.1f} s) "
            f"from {shards}. C = causal, R = real-time (FPS >= {FPS}). "
            f"S = speaking ({ev.num_speaking} seq.), NS = non-speaking "
            f"({ev.num_windows - ev.num_speaking} seq.). FGD in cm² shown ÷{scale['fgd']:g}, "
            f"FGD_acc in (cm/s²)² shown ÷{scale['fgd_acc']:g}, Wrist Var = mean wrist speed in "
            f"cm/s. FGD Avg = mean over batches of {config.batch_clips} clips; NS/S pooled. "
            f"Model: {config.protocol} protocol{_history_note(config)}, {config.steps} "
            f"{config.solver} steps, cfg {config.cfg_scale:g}{_guide_note(config)}"
            f"{_noise_note(config)}, seed {config.seed}.")


def _guide_note(config: EvalConfig) -> str:
    lo, hi = config.guidance_interval
    interval = "" if (lo, hi) == StreamConfig.guidance_interval else f" at {lo:g} <= tau < {hi:g}"
    if set(config.guide) == set(StreamConfig.guide):  # all four, in any order
        return interval and f" (guiding{interval})"
    return f" (guiding {', '.join(config.guide)} only{interval})"


def _noise_note(config: EvalConfig) -> str:
    return "" if config.noise_scale == NOISE_SCALE else f", noise scale {config.noise_scale:g}"


def _history_note(config: EvalConfig) -> str:
    if config.protocol != "stream":
        return ""
    if config.imputation == "trajectory":
        return " (trajectory imputation)"
    if config.history_tokens in (HISTORY_TOKENS, HISTORY_WINDOW):  # the latter: no model to ask
        return ""
    return " (history: all tokens)" if config.history_tokens is None else (
        f" (history: {config.history_tokens} tokens)")


def write_outputs(out: Path, ev: Evaluation, config: EvalConfig, shards: Path, run: Path | None,
                  features: str, windows: TestWindows, speaking: np.ndarray) -> list[Path]:
    """table1/2 .md and .json, windows.json and the plots."""
    out.mkdir(parents=True, exist_ok=True)
    settings = {**asdict(config), "run": None if run is None else str(Path(run).resolve()),
                "shards": str(Path(shards).resolve()),
                "features": features}
    common = {"window_frames": config.window, "num_windows": ev.num_windows,
              "available_windows": ev.available_windows, "requested_windows": config.windows,
              "num_speaking": ev.num_speaking,
              "num_non_speaking": ev.num_windows - ev.num_speaking, "settings": settings}
    paths = []
    if ev.table1:
        caption = _caption1(ev, config, shards)
        atomic_write_text(out / "table1.md", table1_markdown(ev.table1, caption))
        write_json(out / "table1.json", {"caption": caption, **common,
                                          "display_scale": ev.table1[0].table.display_scale,
                                          "units": ev.table1[0].table.units,
                                          "rows": [r.to_dict() for r in ev.table1]})
        paths += [out / "table1.md", out / "table1.json"]
        paths += plot_metric_bars(out / "plots", ev.table1)
        by_part = plot_parts(out / "plots" / "fgd_acc_by_part.png", ev.table1)
        paths += [] if by_part is None else [by_part]
    gt = next((r for r in ev.table1 if r.reference), None)
    gt_head = None if gt is None else gt.shown()["head_angle/avg"]
    if ev.table2:
        caption = (f"Table 2: effect of gaze control on motion ({ev.num_windows} {config.split} "
                   f"windows of {config.window} frames). ∅ = gaze control disabled. Values shown "
                   f"as in Table 1 (Avg)." + ("" if gt_head is None else
                                              f" GT Head Ang. = {gt_head:.2f}."))
        atomic_write_text(out / "table2.md", table2_markdown(ev.table2, caption))
        write_json(out / "table2.json", {"caption": caption, **common,
                                          "gt_head_angle": gt_head,
                                          "rows": [r.to_dict() for r in ev.table2]})
        paths += [out / "table2.md", out / "table2.json"]
        paths.append(plot_gaze_control(out / "plots" / "gaze_control.png", ev.table2, gt_head))
    listing = []
    for i in range(len(windows)):
        sequence, agent, start = windows.dataset.locate(int(windows.indices[i]))
        persons = windows.dataset.shards.entry(sequence).persons
        listing.append({"sequence": sequence, "agent": persons[agent], "start": start,
                        "speaking": bool(speaking[i])})
    if ev.reconstruction is not None:
        caption = (f"VAE reconstruction error per body part ({ev.num_windows} {config.split} "
                   f"windows of {config.window} frames): position = decoded vs true joint "
                   f"(icosahedron centroid), orientation = icosahedron vertices about their "
                   f"centroid; mean over windows (95 % bootstrap interval), in mm.")
        atomic_write_text(out / "reconstruction.md", summary_markdown(ev.reconstruction, caption))
        write_json(out / "reconstruction.json", {"caption": caption, **common,
                                                  "parts": ev.reconstruction})
        paths += [out / "reconstruction.md", out / "reconstruction.json"]
    if ev.latents is not None:
        caption = (f"Latent directions of the Table 1 model row ({ev.latents['windows']} "
                   f"{config.split} windows of {ev.latents['tokens']} tokens): the flow's samples "
                   f"projected on the principal directions of the encoder's latents of the same "
                   f"windows, in bands by the data's cumulative variance; spread = mean square "
                   f"about the data's mean, change = mean squared token-to-token step ÷ twice the "
                   f"data's mean square (0: constant, 1: uncorrelated tokens); 95 % paired "
                   f"bootstrap over windows.")
        atomic_write_text(out / "latents.md", directions_markdown(ev.latents, caption))
        write_json(out / "latents.json", {"caption": caption, **common, **ev.latents})
        paths += [out / "latents.md", out / "latents.json",
                  plot_directions(out / "plots" / "latent_directions.png", ev.latents)]
    write_json(out / "windows.json", {**common, "windows": listing})
    paths.append(out / "windows.json")
    return paths
