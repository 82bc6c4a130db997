"""SMPL-X parameters -> world-space joints, global joint rotations, shell points, eyes, head points.

Embody 3D stores per-frame SMPL-X parameters only, so everything spatial comes from running the
body model forward. The model file (a licensed SMPLX_NEUTRAL.npz, or the procedural body model)
is loaded through the `smplx` package with Embody 3D's settings (300 betas, axis-angle hands, flat
hand mean, neutral), and only what a frame needs is kept: the joint regressor folded into the
shape space (joints never need the mesh), and the template, shape and pose blend shapes and
skinning weights of the shell vertices alone. A frame therefore costs 55 joints plus V shell
vertices, never the full 10,475-vertex mesh.

Memory: outputs take 5,748 bytes per frame with V = 256 (joints 660, rotations 1,980, shell
3,072, eye and head points 36), about 620 MB for an hour (108,000 frames). The working set of one
batch is about 30 KB per frame (pose features, blend shapes, per-vertex skinning transforms),
about 125 MB at the default 4,096 frames, whatever the sequence length. The full mesh would need
126 KB per frame, 13.6 GB per hour.
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sarah_data.body.shell import shell_vertex_ids
from sarah_data.constants import DEFAULT_SHELL_POINTS, JOINT, JOINT_PARENTS, NUM_BETAS, NUM_JOINTS
from sarah_data.gaze import head_points

DEFAULT_BATCH_FRAMES = 4096
POSE_WIDTHS = {"global_orient": 3, "body_pose": 63, "left_hand_pose": 45, "right_hand_pose": 45,
               "transl": 3}
EXPECTED_FILE = ("a SMPL-X model .npz such as SMPLX_NEUTRAL.npz, or the procedural body model "
                 "written by `sarah-fixtures`")
_REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights",
                  "kintree_table", "hands_componentsl", "hands_componentsr", "hands_meanl",
                  "hands_meanr", "lmk_faces_idx", "lmk_bary_coords")


class BodyModelError(Exception):
    """A body model file that cannot be used: `path` names it, `reason` says why."""

    def __init__(self, path: Path | str, reason: str):
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


@dataclass(frozen=True)
class BodyFrames:
    """Per-frame body geometry in world space, metres, numpy float32."""

    joints: np.ndarray  # (T,55,3)
    rotations: np.ndarray  # (T,55,3,3) global joint rotations
    shell: np.ndarray  # (T,V,3)
    eye_mid: np.ndarray  # (T,3) midpoint of the eye joints 23 and 24
    head_front: np.ndarray  # (T,3) head joint + HEAD_HALF_DEPTH along the head's +z
    head_back: np.ndarray  # (T,3) head joint - HEAD_HALF_DEPTH along the head's +z

    def __len__(self) -> int:
        return len(self.joints)


def _resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _load_smplx(path: Path):
    """The smplx package's SMPLX module for `path` and the file's own v_template (float64).

    Raises a BodyModelError saying what is wrong with the file.
    """
    if not path.is_file():
        raise BodyModelError(path, f"no such body model file; expected {EXPECTED_FILE}")
    if path.suffix.lower() != ".npz":
        raise BodyModelError(path, f"not an .npz file; expected {EXPECTED_FILE}")
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            v_template = np.asarray(data["v_template"], dtype=np.float64) if "v_template" in keys else None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise BodyModelError(path, f"unreadable ({error}); expected {EXPECTED_FILE}") from None
    missing = [k for k in _REQUIRED_KEYS if k not in keys]
    if missing:
        raise BodyModelError(path, f"missing arrays {', '.join(missing)}; expected {EXPECTED_FILE}")
    import smplx  # deferred: importing it is slow and only loading needs it

    try:
        full = smplx.SMPLX(model_path=str(path), num_betas=NUM_BETAS, use_pca=False,
                           flat_hand_mean=True, gender="neutral", ext="npz")
    except Exception as error:  # whatever smplx trips on, the file is the problem
        raise BodyModelError(path, f"the smplx package cannot load it ({type(error).__name__}: "
                                   f"{error}); expected {EXPECTED_FILE}") from error
    return full, v_template


def _depth_levels(parents: tuple[int, ...]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Joints grouped by depth in the tree (root excluded), so FK runs one level at a time."""
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    levels = []
    for d in range(1, max(depth) + 1):
        idx = [j for j in range(len(parents)) if depth[j] == d]
        levels.append((torch.tensor(idx), torch.tensor([parents[j] for j in idx])))
    return levels


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, (...,3) -> (...,3,3), stable at zero angle."""
    theta = torch.linalg.vector_norm(rotvec, dim=-1)[..., None, None]
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*rotvec.shape[:-1], 3, 3)
    # sin(t)/t and (1 - cos t)/t^2 = 2 sin^2(t/2)/t^2, written with sinc to avoid 0/0.
    a = torch.sinc(theta / torch.pi)
    b = 0.5 * torch.sinc(theta / (2.0 * torch.pi)) ** 2
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a * K + b * (K @ K)


class BodyModel:
    """A SMPL-X-format body model reduced to what per-frame joints and shell points need."""

    def __init__(self, *, path: Path, sha256: str, num_betas: int, shell_ids: np.ndarray,
                 joint_template: torch.Tensor, joint_dirs: torch.Tensor,
                 shell_template: torch.Tensor, shell_dirs: torch.Tensor,
                 shell_posedirs: torch.Tensor, shell_weights: torch.Tensor, device: torch.device):
        self._path = path
        self._sha256 = sha256
        self._num_betas = num_betas
        self._shell_ids = shell_ids
        self.device = device
        self._joint_template = joint_template.to(device)  # (55,3)
        self._joint_dirs = joint_dirs.to(device)  # (B, 55*3)
        self._shell_template = shell_template.to(device)  # (V,3)
        self._shell_dirs = shell_dirs.to(device)  # (B, V*3)
        self._shell_posedirs_t = shell_posedirs.t().contiguous().to(device)  # (V*3, 486)
        self._shell_weights = shell_weights.to(device)  # (V,55)
        self._levels = [(i.to(device), p.to(device)) for i, p in _depth_levels(JOINT_PARENTS)]

    @classmethod
    def from_file(cls, path: str | os.PathLike, device: str | torch.device | None = None,
                  shell_points: int = DEFAULT_SHELL_POINTS) -> "BodyModel":
        """Load a SMPL-X-format .npz through the smplx package and keep the per-frame parts."""
        path = Path(path)
        full, file_template = _load_smplx(path)
        v_template = full.v_template.double()  # (N,3)
        shapedirs = full.shapedirs.double()  # (N,3,B)
        J_regressor = full.J_regressor.double()  # (55,N)
        parents = tuple(int(p) for p in full.parents)
        if J_regressor.shape[0] != NUM_JOINTS or parents != tuple(JOINT_PARENTS):
            raise BodyModelError(path, "its kinematic tree is not SMPL-X's 55 joints; "
                                       f"expected {EXPECTED_FILE}")
        num_verts, num_betas = v_template.shape[0], shapedirs.shape[-1]
        if file_template.shape != (num_verts, 3) or J_regressor.shape[1] != num_verts:
            raise BodyModelError(path, f"inconsistent shapes: v_template {file_template.shape}, "
                                       f"J_regressor {tuple(J_regressor.shape)}; expected {EXPECTED_FILE}")
        # Sampled on the file's own numbers: float32 rounding could flip near-ties between picks.
        ids = shell_vertex_ids(file_template, shell_points)
        idx = torch.from_numpy(ids)
        posedirs = full.posedirs.reshape(full.posedirs.shape[0], num_verts, 3)[:, idx]
        return cls(
            path=path, sha256=_sha256(path), num_betas=num_betas, shell_ids=ids,
            joint_template=(J_regressor @ v_template).float(),
            joint_dirs=torch.einsum("jn,nck->kjc", J_regressor, shapedirs).reshape(num_betas, -1)
            .float(),
            shell_template=full.v_template[idx].clone(),
            shell_dirs=full.shapedirs[idx].permute(2, 0, 1).reshape(num_betas, -1).clone(),
            shell_posedirs=posedirs.reshape(posedirs.shape[0], -1).clone(),
            shell_weights=full.lbs_weights[idx].clone(),
            device=_resolve_device(device),
        )

    @property
    def shell_ids(self) -> np.ndarray:
        """Vertex ids (V,) int64 of the shell points in the model's mesh."""
        return self._shell_ids.copy()

    @property
    def name(self) -> str:
        return self._path.stem

    @property
    def sha256(self) -> str:
        return self._sha256

    @property
    def num_betas(self) -> int:
        return self._num_betas

    @property
    def gender(self) -> str:
        """"female" or "male" for a gendered SMPL-X file (by its name), else "neutral"."""
        name = self.name.lower()
        return "female" if "female" in name else "male" if "male" in name else "neutral"

    def shape_betas(self, betas: np.ndarray) -> np.ndarray:
        """Betas (n,) or (T, n) padded or cut to this model's count (float64, (T, B) or (B,))."""
        betas = np.asarray(betas, dtype=np.float64)
        rows = np.atleast_2d(betas)
        _, prepared = self._prepare({"betas": rows, **{k: np.zeros((len(rows), w))
                                                        for k, w in POSE_WIDTHS.items()}})
        return prepared["betas"] if betas.ndim == 2 else prepared["betas"][0]

    def rest_joints(self, betas: np.ndarray) -> np.ndarray:
        """Joints (55, 3) float64 of the body with ``betas`` (n,) at zero pose and translation:
        the skeleton that exports (SMPL-X ``trans``, BVH offsets) are built on."""
        shaped = torch.from_numpy(self.shape_betas(betas)).to(self._joint_dirs.device).double()
        rest = self._joint_template.double() + (shaped @ self._joint_dirs.double()).reshape(NUM_JOINTS, 3)
        return rest.cpu().numpy()

    def _prepare(self, params: dict[str, np.ndarray]) -> tuple[int, dict[str, np.ndarray]]:
        missing = [k for k in ("betas", *POSE_WIDTHS) if k not in params]
        if missing:
            raise ValueError(f"body parameters lack {', '.join(missing)}")
        arrays = {k: np.asarray(params[k]) for k in ("betas", *POSE_WIDTHS)}
        frames = len(arrays["transl"]) if arrays["transl"].ndim == 2 else -1
        for key, width in POSE_WIDTHS.items():
            if arrays[key].shape != (frames, width):
                raise ValueError(f"body parameter {key} has shape {arrays[key].shape}, expected "
                                 f"({frames if frames >= 0 else 'T'}, {width})")
        betas = arrays["betas"]
        if betas.ndim == 1:
            betas = np.broadcast_to(betas, (frames, len(betas)))
        if betas.ndim != 2 or len(betas) != frames:
            raise ValueError(f"body parameter betas has shape {arrays['betas'].shape}, "
                             f"expected ({frames}, n)")
        if betas.shape[1] > self._num_betas:
            if np.any(betas[:, self._num_betas:] != 0):
                raise ValueError(f"betas have {betas.shape[1]} coefficients but body model "
                                 f"{self.name} has only {self._num_betas} shape components")
            betas = betas[:, :self._num_betas]
        elif betas.shape[1] < self._num_betas:
            betas = np.pad(betas, ((0, 0), (0, self._num_betas - betas.shape[1])))
        arrays["betas"] = betas
        return frames, arrays

    def forward(self, params: dict[str, np.ndarray],
                batch_frames: int = DEFAULT_BATCH_FRAMES) -> BodyFrames:
        """Run the body for every frame of `params` (Embody 3D's arrays), `batch_frames` at a time.

        Keys: betas (T,n) or (n,), body_pose (T,63), global_orient (T,3), transl (T,3),
        left_hand_pose (T,45), right_hand_pose (T,45); axis-angle, flat hand mean. Jaw, eyes and
        expression are zero (Embody 3D has none).
        """
        if batch_frames < 1:
            raise ValueError(f"batch_frames must be positive, got {batch_frames}")
        frames, arrays = self._prepare(params)
        num_shell = len(self._shell_ids)
        joints = np.empty((frames, NUM_JOINTS, 3), dtype=np.float32)
        rotations = np.empty((frames, NUM_JOINTS, 3, 3), dtype=np.float32)
        shell = np.empty((frames, num_shell, 3), dtype=np.float32)
        for start in range(0, frames, batch_frames):
            stop = min(start + batch_frames, frames)
            # A copy: inputs may be read-only (memory-mapped), which torch cannot wrap.
            batch = {k: torch.from_numpy(np.array(v[start:stop], dtype=np.float32)).to(self.device)
                     for k, v in arrays.items()}
            j, r, s = self._forward_batch(batch)
            joints[start:stop] = j.cpu().numpy()
            rotations[start:stop] = r.cpu().numpy()
            shell[start:stop] = s.cpu().numpy()
        eye_mid = 0.5 * (joints[:, JOINT["left_eye_smplhf"]] + joints[:, JOINT["right_eye_smplhf"]])
        front, back = head_points(joints[:, JOINT["head"]], rotations[:, JOINT["head"]])
        return BodyFrames(joints, rotations, shell, eye_mid.astype(np.float32),
                          front.astype(np.float32), back.astype(np.float32))

    @torch.inference_mode()
    def _forward_batch(self, p: dict[str, torch.Tensor]):
        """One batch of n frames -> joints (n,55,3), global rotations (n,55,3,3), shell (n,V,3).

        Computed joint-major (55, n, ...) and vertex-major (V, n, ...), so tree levels and
        vertices gather whole contiguous blocks.
        """
        n = len(p["transl"])
        face = torch.zeros(n, 9, dtype=torch.float32, device=self.device)  # jaw and both eyes
        pose = torch.cat([p["global_orient"], p["body_pose"], face, p["left_hand_pose"],
                          p["right_hand_pose"]], dim=1).reshape(n, NUM_JOINTS, 3)
        local = axis_angle_to_matrix(pose.transpose(0, 1).contiguous())  # (55,n,3,3)

        # Most sequences have one body shape: blend each distinct betas row once, and broadcast
        # (m = 1) when the whole batch shares it.
        betas = p["betas"]
        if bool((betas == betas[:1]).all()):
            # The usual case; torch.unique would sort every row to find it (~10 % of a forward).
            # A fresh tensor like unique's: BLAS may round differently for differently aligned
            # inputs, and the numpy-owned batch has no fixed alignment.
            shapes, which = betas[:1].clone(), torch.zeros(n, dtype=torch.long, device=betas.device)
        else:
            shapes, which = torch.unique(betas, dim=0, return_inverse=True)
        rest = self._joint_template + (shapes @ self._joint_dirs).reshape(-1, NUM_JOINTS, 3)
        shaped = self._shell_template + (shapes @ self._shell_dirs).reshape(len(shapes), -1, 3)
        if len(shapes) > 1:
            rest, shaped = rest[which], shaped[which]
        rest = rest.transpose(0, 1).contiguous()  # (55,m,3)
        shaped = shaped.transpose(0, 1)  # (V,m,3)

        eye = torch.eye(3, dtype=local.dtype, device=local.device)
        pose_features = (local[1:] - eye).reshape(NUM_JOINTS - 1, n, 9).permute(0, 2, 1).reshape(-1, n)
        offsets = (self._shell_posedirs_t @ pose_features).reshape(-1, 3, n).permute(0, 2, 1)
        posed = shaped + offsets  # (V,n,3)

        g_rot = torch.empty_like(local)
        g_pos = torch.empty(NUM_JOINTS, n, 3, dtype=local.dtype, device=local.device)
        g_rot[0], g_pos[0] = local[0], rest[0]
        for idx, parent in self._levels:
            parent_rot = g_rot[parent]
            g_rot[idx] = parent_rot @ local[idx]
            bone = (rest[idx] - rest[parent]).unsqueeze(-1)
            g_pos[idx] = (parent_rot @ bone).squeeze(-1) + g_pos[parent]

        # Skinning transforms map rest-pose points to posed ones: x -> G_R x + (G_t - G_R J_rest).
        offset = g_pos - (g_rot @ rest.unsqueeze(-1)).squeeze(-1)
        per_joint = torch.cat([g_rot.reshape(NUM_JOINTS, n, 9), offset], dim=-1)  # (55,n,12)
        per_vertex = (self._shell_weights @ per_joint.reshape(NUM_JOINTS, -1)).reshape(-1, n, 12)
        shell = torch.einsum("vnik,vnk->vni", per_vertex[..., :9].reshape(-1, n, 3, 3), posed)
        shell = shell + per_vertex[..., 9:]
        transl = p["transl"].unsqueeze(1)
        return g_pos.transpose(0, 1) + transl, g_rot.transpose(0, 1), shell.transpose(0, 1) + transl
