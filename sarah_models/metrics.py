"""Evaluation metrics of the paper's section 4: FGD, FGD_acc, foot slide, wrist speed, head angle.

Every metric is reported three ways: Avg, NS (non-speaking clips) and S (speaking clips).

* FGD, FGD_acc: S and NS are one Fréchet distance each between the pooled generated and pooled
  ground-truth samples of that category; Avg is the mean of per-batch Fréchet distances over
  consecutive batches of `batch_clips` clips (all categories mixed). Small batches bias the
  covariance, so Avg is not a combination of S and NS and usually exceeds both.
* Foot slide, wrist speed, head angle: one value per generated clip; S and NS are the means over
  the clips of each category; Avg is their clip-count-weighted mean (= the mean over all clips).

Clips hold metres and seconds. Reported values are in centimetres (the paper's MHR meshes are in
centimetres, and its thresholds and table magnitudes read naturally in them):

    metric        per-sample definition                                     unit        table shows
    FGD           shell vertex positions of one frame, window frame, (V*3,)  cm^2        value / 10
    FGD_acc       (x[t+1] - 2 x[t] + x[t-1]) * fps^2 of the same, (V*3,)     (cm/s^2)^2  value / 1e5
    foot_slide    fraction of steps with a foot below 5 cm moving > 3 cm/s   -           value
    wrist_speed   mean 3D speed of both wrists                               cm/s        value
    head_angle    mean gaze score toward the user (floor plane)              -           value

"FGD (x10^1)" in the paper's table header is read as "shown in units of 10^1": shown = raw / 10.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy import linalg

from sarah_data import frames, gaze, icosahedron
from sarah_data.constants import FPS, JOINT, NUM_JOINTS

METRICS = ("fgd", "fgd_acc", "foot_slide", "wrist_speed", "head_angle")


@dataclass(frozen=True)
class MetricsConfig:
    """Evaluation settings; defaults are the paper's values where it states them."""

    # Clips per batch for the FGD / FGD_acc Avg column. The paper does not state it; 16 is its
    # per-GPU batch size, and its remark that a batch may hold "too few clips of one category"
    # implies batches of this order.
    batch_clips: int = 16
    foot_max_height: float = 0.05  # m: "near the ground (<5 cm)"
    foot_min_speed: float = 0.03  # m/s: "moving horizontally (>3 cm/s)"
    foot_joints: tuple[str, ...] = ("left_foot", "right_foot")
    wrist_joints: tuple[str, ...] = ("left_wrist", "right_wrist")
    head_joint: str = "head"
    root_joint: str = "pelvis"
    # Re-normalize every clip to its window frame (agent's pelvis at frame 0 at the origin facing
    # +z) before FGD, so world-frame clips score like window-frame ones. Idempotent on clips that
    # are already in the window frame.
    normalize_window: bool = True
    report_unit: float = 0.01  # metres per reported length unit: centimetres
    fd_ridge: float = 1e-6  # relative ridge for ill-conditioned covariances (see frechet_distance)
    display_scale: dict[str, float] = field(default_factory=lambda: {
        "fgd": 10.0, "fgd_acc": 1e5, "foot_slide": 1.0, "wrist_speed": 1.0, "head_angle": 1.0})


# --------------------------------------------------------------------------- Fréchet distance


class FrechetRidgeWarning(RuntimeWarning):
    """A ridge was added to the covariances because their product's square root was unreliable."""


def _as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _sqrtm_problem(root: np.ndarray, product: np.ndarray, caught: list, imag_tol: float) -> str | None:
    """Why `root` is not a trustworthy square root of `product`, or None if it is."""
    if not np.all(np.isfinite(root)):
        return "non-finite square root"
    for w in caught:
        if issubclass(w.category, linalg.LinAlgWarning):
            return f"ill-conditioned product ({w.message})"
    scale = max(float(np.abs(root.real).max()), np.finfo(np.float64).tiny)
    if np.iscomplexobj(root) and float(np.abs(root.imag).max()) > imag_tol * scale:
        return f"imaginary part {np.abs(root.imag).max():.3g} vs real scale {scale:.3g}"
    residual = np.linalg.norm(root @ root - product) / max(np.linalg.norm(product), 1e-300)
    if residual > 1e-6:
        return f"relative residual {residual:.3g} of root @ root"
    return None


def frechet_distance_from_moments(mean_a, cov_a, mean_b, cov_b, ridge: float = 1e-6,
                                  max_retries: int = 6, imag_tol: float = 1e-3) -> float:
    """||mu_a - mu_b||^2 + tr(C_a + C_b - 2 (C_a C_b)^(1/2)) of two Gaussians, in float64.

    The square root is scipy.linalg.sqrtm of the covariance product. If it is non-finite, scipy
    reports the product singular or ill-conditioned, its imaginary residue exceeds `imag_tol`
    times its real scale, or root @ root misses the product, a ridge eps*I is added to both
    covariances and the root retried, eps starting at `ridge` times the mean variance and growing
    tenfold per retry; the distance is then that of the ridged Gaussians (so FD(x, x) stays 0).
    A small imaginary residue is dropped; a large one after all retries raises.
    """
    mean_a, mean_b = (np.asarray(_as_numpy(m), dtype=np.float64) for m in (mean_a, mean_b))
    cov_a, cov_b = (np.asarray(_as_numpy(c), dtype=np.float64) for c in (cov_a, cov_b))
    dim = mean_a.shape[0]
    if mean_b.shape != (dim,) or cov_a.shape != (dim, dim) or cov_b.shape != (dim, dim):
        raise ValueError(f"Fréchet distance: mismatched shapes {mean_a.shape}, {cov_a.shape}, "
                         f"{mean_b.shape}, {cov_b.shape}")
    variance_scale = (np.trace(cov_a) + np.trace(cov_b)) / (2 * dim)
    eps_step = ridge * variance_scale if variance_scale > 0 else ridge
    eye = np.eye(dim)
    offset, problem = 0.0, None
    for attempt in range(max_retries + 1):
        ridged_a, ridged_b = cov_a + offset * eye, cov_b + offset * eye
        product = ridged_a @ ridged_b
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            root = linalg.sqrtm(product)
        problem = _sqrtm_problem(root, product, caught, imag_tol)
        if problem is None:
            break
        offset = eps_step * 10.0 ** attempt
    else:
        raise FloatingPointError(f"Fréchet distance: no reliable covariance square root after "
                                 f"{max_retries} ridge retries (last: {problem})")
    if offset > 0:
        warnings.warn(f"Fréchet distance: added ridge {offset:.3g}*I to both covariances",
                      FrechetRidgeWarning, stacklevel=2)
    diff = mean_a - mean_b
    value = float(diff @ diff + np.trace(ridged_a) + np.trace(ridged_b) - 2.0 * np.trace(root.real))
    # Rounding can leave an exact match a hair below zero; anything larger is a real failure.
    tolerance = 1e-6 * max(float(np.trace(ridged_a) + np.trace(ridged_b)), 1.0)
    if value < -tolerance:
        raise FloatingPointError(f"Fréchet distance: negative result {value:.3g}")
    return max(value, 0.0)


def frechet_distance(feats_a, feats_b, ridge: float = 1e-6) -> float:
    """Fréchet distance between Gaussians fitted to samples (N,D) and (M,D) (float64 moments)."""
    a, b = (np.asarray(_as_numpy(f), dtype=np.float64) for f in (feats_a, feats_b))
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1] or len(a) < 2 or len(b) < 2:
        raise ValueError(f"Fréchet distance needs two (N>=2, D) sample arrays; got {a.shape}, {b.shape}")
    return frechet_distance_from_moments(a.mean(0), np.atleast_2d(np.cov(a, rowvar=False)),
                                         b.mean(0), np.atleast_2d(np.cov(b, rowvar=False)), ridge=ridge)


@dataclass
class Moments:
    """Running count, mean and centred scatter of (N,D) samples, merged exactly (Chan et al.).

    Pooling 2048 clips x 400 frames would not fit in memory as one array; merging per-clip
    centred moments avoids both that and the cancellation of a raw sum of squares.
    """

    count: int = 0
    mean: np.ndarray | None = None
    scatter: np.ndarray | None = None

    def add(self, samples: np.ndarray) -> None:
        x = np.asarray(samples, dtype=np.float64)
        mean = x.mean(0)
        centred = x - mean
        self.merge(Moments(len(x), mean, centred.T @ centred))

    def merge(self, other: "Moments") -> None:
        if other.count == 0:
            return
        if self.count == 0:
            self.count, self.mean, self.scatter = other.count, other.mean.copy(), other.scatter.copy()
            return
        total = self.count + other.count
        delta = other.mean - self.mean
        self.scatter = self.scatter + other.scatter + np.outer(delta, delta) * (self.count * other.count / total)
        self.mean = self.mean + delta * (other.count / total)
        self.count = total

    @property
    def covariance(self) -> np.ndarray:
        return self.scatter / (self.count - 1)


def _moments_distance(a: Moments, b: Moments, ridge: float) -> float:
    if a.count < 2 or b.count < 2:
        return math.nan
    return frechet_distance_from_moments(a.mean, a.covariance, b.mean, b.covariance, ridge=ridge)


# --------------------------------------------------------------------------- per-clip metrics


def _joint_ids(names: Sequence[str]) -> list[int]:
    return [JOINT[name] for name in names]


def foot_slide(joint_positions, fps: float = FPS, max_height: float = 0.05, min_speed: float = 0.03,
               foot_joints: Sequence[str] = ("left_foot", "right_foot")) -> float:
    """Fraction of frame steps (t-1 -> t) in which at least one foot slides; in [0, 1].

    A foot slides during a step when its joint is below `max_height` (metres above the floor
    y = 0) at both ends of the step and its horizontal (x, z) speed over the step exceeds
    `min_speed` (m/s). joint_positions: (T,J,3) in metres, y up.
    """
    p = np.asarray(_as_numpy(joint_positions), dtype=np.float64)[:, _joint_ids(foot_joints)]
    if len(p) < 2:
        raise ValueError(f"foot_slide needs at least 2 frames, got {len(p)}")
    low = np.maximum(p[1:, :, 1], p[:-1, :, 1]) < max_height
    speed = np.linalg.norm(np.diff(p[..., [0, 2]], axis=0), axis=-1) * fps
    return float(np.mean(np.any(low & (speed > min_speed), axis=1)))


def wrist_speed(joint_positions, fps: float = FPS,
                wrist_joints: Sequence[str] = ("left_wrist", "right_wrist")) -> float:
    """Mean 3D speed of the wrists over all frame steps and both wrists, in m/s."""
    p = np.asarray(_as_numpy(joint_positions), dtype=np.float64)[:, _joint_ids(wrist_joints)]
    if len(p) < 2:
        raise ValueError(f"wrist_speed needs at least 2 frames, got {len(p)}")
    return float(np.mean(np.linalg.norm(np.diff(p, axis=0), axis=-1)) * fps)


def head_angle(head_position, head_rotation, user_head_xz) -> float:
    """Mean gaze score of the agent toward the user over frames, in [-1, 1].

    head_position (T,3), head_rotation (T,3,3): the agent's head joint; user_head_xz (T,2) the
    user's floor-projected head, in the same frame. Uses gaze.head_points and gaze.gaze_score,
    the definitions that produce the training data's gaze score.
    """
    front, back = gaze.head_points(np.asarray(_as_numpy(head_position), dtype=np.float64),
                                   np.asarray(_as_numpy(head_rotation), dtype=np.float64))
    return float(np.mean(gaze.gaze_score(front, back, np.asarray(_as_numpy(user_head_xz), dtype=np.float64))))


def accelerations(points, fps: float = FPS) -> np.ndarray:
    """Second finite difference over time times fps^2: (T,...) -> (T-2,...), units/s^2."""
    p = np.asarray(_as_numpy(points), dtype=np.float64)
    return (p[2:] - 2.0 * p[1:-1] + p[:-2]) * fps**2


# --------------------------------------------------------------------------- clips and tables


@dataclass
class Clip:
    """One evaluated clip: the agent's motion and the user's floor head trajectory.

    icosahedra (T,55,12,3) and shell (T,V,3) in metres, y up, floor at y = 0, world or window
    frame; user_head (T,2) as (x, z) in the same frame; fps frames per second.
    Torch tensors are accepted and converted to numpy arrays.
    """

    icosahedra: np.ndarray
    shell: np.ndarray
    user_head: np.ndarray
    fps: float = FPS

    def __post_init__(self) -> None:
        # Kept in the given float precision (float32 halves memory); metrics compute in float64.
        for name in ("icosahedra", "shell", "user_head"):
            value = np.asarray(_as_numpy(getattr(self, name)))
            setattr(self, name, value if np.issubdtype(value.dtype, np.floating) else value.astype(np.float64))
        frames_ = self.icosahedra.shape[0] if self.icosahedra.ndim else 0
        problems = []
        if self.icosahedra.shape[1:] != (NUM_JOINTS, 12, 3):
            problems.append(f"icosahedra shape {self.icosahedra.shape}, want (T,{NUM_JOINTS},12,3)")
        if self.shell.ndim != 3 or self.shell.shape[0] != frames_ or self.shell.shape[2] != 3:
            problems.append(f"shell shape {self.shell.shape}, want ({frames_},V,3)")
        if self.user_head.shape != (frames_, 2):
            problems.append(f"user_head shape {self.user_head.shape}, want ({frames_},2)")
        if frames_ < 3:
            problems.append(f"{frames_} frames; accelerations need at least 3")
        if not self.fps > 0:
            problems.append(f"fps {self.fps} is not positive")
        if problems:
            raise ValueError("Clip: " + "; ".join(problems))
        for name in ("icosahedra", "shell", "user_head"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"Clip: {name} contains non-finite values")

    @property
    def num_frames(self) -> int:
        return self.icosahedra.shape[0]


@dataclass
class CategoryValues:
    """One metric's Avg, NS and S values (NaN where a category has no clips)."""

    avg: float
    ns: float
    s: float


@dataclass
class MetricsTable:
    """Raw metric values (in `units`) with the counts and settings that produced them."""

    values: dict[str, CategoryValues]
    units: dict[str, str]
    display_scale: dict[str, float]
    num_clips: int
    num_speaking: int
    num_non_speaking: int
    window_frames: int
    fps: float
    batch_clips: int
    num_batches: int

    def to_row(self, scale: bool = True) -> dict[str, float]:
        """{"fgd/avg": ..., "fgd/ns": ..., "fgd/s": ..., ...}; scale=True divides by the table's
        display factors (FGD / 10, FGD_acc / 1e5), as the paper's Table 1 shows them."""
        row = {}
        for name in METRICS:
            factor = self.display_scale[name] if scale else 1.0
            for column, value in asdict(self.values[name]).items():
                row[f"{name}/{column}"] = value / factor
        return row

    def to_dict(self) -> dict:
        """JSON-ready, raw (unscaled) values; NaN becomes None."""
        out = asdict(self)
        out["values"] = {name: {k: (None if math.isnan(v) else v) for k, v in values.items()}
                         for name, values in out["values"].items()}
        return out


def _decoded(clip: Clip):
    positions, rotations = icosahedron.decode(np.asarray(clip.icosahedra, dtype=np.float64))
    return positions, rotations


def _fgd_samples(clip: Clip, positions, rotations, cfg: MetricsConfig):
    """(poses (T, V*3), accelerations (T-2, V*3)) of a clip's shell in the window frame, metres."""
    shell = np.asarray(clip.shell, dtype=np.float64)
    if cfg.normalize_window:
        root = JOINT[cfg.root_joint]
        shell = frames.window_transform(positions[0, root], rotations[0, root]).apply_points(shell)
    flat = shell.reshape(len(shell), -1)
    return flat, accelerations(flat, clip.fps)


def _per_clip_metrics(clip: Clip, positions, rotations, cfg: MetricsConfig) -> dict[str, float]:
    head = JOINT[cfg.head_joint]
    return {
        "foot_slide": foot_slide(positions, clip.fps, cfg.foot_max_height, cfg.foot_min_speed, cfg.foot_joints),
        "wrist_speed": wrist_speed(positions, clip.fps, cfg.wrist_joints),
        "head_angle": head_angle(positions[:, head], rotations[:, head], clip.user_head),
    }


def _check_like(kind: str, index: int, clip: Clip, reference: Clip) -> None:
    if (clip.num_frames, clip.fps, clip.shell.shape[1]) != (
            reference.num_frames, reference.fps, reference.shell.shape[1]):
        raise ValueError(f"evaluate: {kind} clip {index} has {clip.num_frames} frames at {clip.fps} fps "
                         f"with {clip.shell.shape[1]} shell points; generated clip 0 has "
                         f"{reference.num_frames} at {reference.fps} with {reference.shell.shape[1]}")


def category_means(per_clip: np.ndarray, speaking: np.ndarray) -> CategoryValues:
    """Avg, NS and S of a per-clip metric: Avg is the mean over all clips, i.e. the clip-count
    weighted mean of the NS and S means (NaN for a category without clips)."""
    ns, s = (float(per_clip[speaking == cat].mean()) if np.any(speaking == cat) else math.nan
             for cat in (False, True))
    return CategoryValues(float(per_clip.mean()), ns, s)


def metric_units(report_unit: float) -> dict[str, str]:
    unit = {0.01: "cm", 1.0: "m", 0.001: "mm"}.get(report_unit, f"{report_unit} m")
    return {"fgd": f"{unit}^2", "fgd_acc": f"({unit}/s^2)^2", "foot_slide": "fraction of frame steps",
            "wrist_speed": f"{unit}/s", "head_angle": "gaze score in [-1, 1]"}


def evaluate(generated: Sequence[Clip], ground_truth: Sequence[Clip], speaking,
             batch_clips: int | None = None, config: MetricsConfig | None = None) -> MetricsTable:
    """Score generated clips against their ground truth (clip i of each is the same window).

    speaking (N,) bool: whether clip i is a speaking clip (sarah_data.speaking's clip rule on the
    agent's audio). FGD batches are consecutive runs of `batch_clips` clips in the given order;
    the last batch may be shorter. Per-clip metrics are computed on the generated clips only.
    The clip sequences may be lazy (any __len__/__getitem__); each clip is read once, in order.
    All clips must share one length, frame rate and shell size.
    """
    cfg = config or MetricsConfig()
    if batch_clips is not None:
        cfg = replace(cfg, batch_clips=batch_clips)
    if cfg.batch_clips < 1:
        raise ValueError(f"evaluate: batch_clips must be positive, got {cfg.batch_clips}")
    speaking = np.asarray(_as_numpy(speaking)).astype(bool).reshape(-1)
    if len(generated) != len(ground_truth) or len(generated) != len(speaking) or len(generated) == 0:
        raise ValueError(f"evaluate: {len(generated)} generated clips, {len(ground_truth)} ground-truth "
                         f"clips and {len(speaking)} speaking flags; need equal, non-zero counts")
    reference = generated[0]

    per_clip = {name: [] for name in ("foot_slide", "wrist_speed", "head_angle")}
    pooled = {(kind, role, cat): Moments() for kind in ("fgd", "fgd_acc")
              for role in ("gen", "gt") for cat in (False, True)}
    batch_values = {"fgd": [], "fgd_acc": []}
    for start in range(0, len(generated), cfg.batch_clips):
        batch = {(kind, role): Moments() for kind in ("fgd", "fgd_acc") for role in ("gen", "gt")}
        for i in range(start, min(start + cfg.batch_clips, len(generated))):
            for role, clip in (("gen", generated[i]), ("gt", ground_truth[i])):
                _check_like("generated" if role == "gen" else "ground-truth", i, clip, reference)
                positions, rotations = _decoded(clip)
                poses, acc = _fgd_samples(clip, positions, rotations, cfg)
                for kind, samples in (("fgd", poses), ("fgd_acc", acc)):
                    clip_moments = Moments()
                    clip_moments.add(samples)
                    batch[kind, role].merge(clip_moments)
                    pooled[kind, role, bool(speaking[i])].merge(clip_moments)
                if role == "gen":
                    for name, value in _per_clip_metrics(clip, positions, rotations, cfg).items():
                        per_clip[name].append(value)
        for kind in batch_values:
            batch_values[kind].append(_moments_distance(batch[kind, "gen"], batch[kind, "gt"], cfg.fd_ridge))

    length = 1.0 / cfg.report_unit  # metres -> reported unit
    values = {}
    for kind in ("fgd", "fgd_acc"):
        ns, s = (_moments_distance(pooled[kind, "gen", cat], pooled[kind, "gt", cat], cfg.fd_ridge)
                 for cat in (False, True))
        values[kind] = CategoryValues(float(np.mean(batch_values[kind])) * length**2, ns * length**2, s * length**2)
    for name, clip_values in per_clip.items():
        values[name] = category_means(np.asarray(clip_values) * (length if name == "wrist_speed" else 1.0),
                                      speaking)

    return MetricsTable(
        values=values,
        units=metric_units(cfg.report_unit),
        display_scale=dict(cfg.display_scale),
        num_clips=len(generated), num_speaking=int(speaking.sum()),
        num_non_speaking=int((~speaking).sum()), window_frames=reference.num_frames,
        fps=float(reference.fps), batch_clips=cfg.batch_clips,
        num_batches=len(batch_values["fgd"]),
    )
