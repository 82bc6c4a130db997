"""One dyad, raw files in, model-ready arrays out: the per-sequence task of `sarah-prep`.

The task runs wherever the executor puts it (this process, a spawned worker, a Ray worker), so
it takes only picklable arguments, loads the body model and feature extractors once per process,
and writes its result to a work file named after the sequence instead of sending arrays back.
The work file is a one-sequence shard file (compressed here, in parallel; the parent copies its
chunks into the shards without decoding them) plus, for train sequences, the sequence's share of
the normalization statistics (so the parent never reads the arrays back).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import __version__, gaze, icosahedron
from .config import PrepConfig
from .constants import JOINT, JOINT_NAMES
from .embody3d import PairRecord, load_person
from .loading import DataProblem
from .atomic import OutOfSpace, atomic_write_bytes, out_of_space
from .shards import (ProcessedSequence, ShardAttrs, atomic_h5, create_group,
                     file_sha256, write_sequence)

_MODELS: dict[tuple, object] = {}  # per process: loading a body model or HuBERT once is enough
WORK_FORMAT = 3  # 1: npz arrays; 2: one-sequence shard file + statistics moments; 3: + body shape, NaN repair
MOMENTS_GROUP = ".moments"  # in a work file; sequence names never start with "."


@dataclass
class TaskResult:
    """What the parent learns about one sequence; the arrays stay in the work file."""

    sequence: str
    status: str  # "ok", "skipped" (bad input) or "failed" (a bug: the traceback is kept)
    reason: str = ""
    frames: int = 0
    warnings: list[str] = field(default_factory=list)
    sources: list[dict] = field(default_factory=list)  # path, bytes, sha256 of every input file
    # Frames with NaN/inf parameters, both persons: tracked ones (now marked untracked) and
    # untracked ones (allowed); embody3d.load_person fills both with finite values.
    nonfinite: dict[str, int] = field(default_factory=lambda: {"tracked": 0, "untracked": 0})
    detail: str = ""


def _body_model(path: str, config: PrepConfig):
    from .body import BodyModel

    key = ("body", path, config.device, config.shell_points)
    if key not in _MODELS:
        _MODELS[key] = BodyModel.from_file(path, device=config.device, shell_points=config.shell_points)
    return _MODELS[key]


def _extractor(name: str, config: PrepConfig):
    from .features import get_extractor

    options = config.extractor_options(name)
    key = ("features", name, json.dumps(options, sort_keys=True), config.device)
    if key not in _MODELS:
        _MODELS[key] = get_extractor(name, **options).to(config.device)
    return _MODELS[key]


def shard_attrs(body_model_path: str, body_model_sha: str, config: PrepConfig) -> ShardAttrs:
    """The root attributes of this run's shards (from the models this process has loaded)."""
    from .icosahedron import TEMPLATE

    body = _body_model(body_model_path, config)
    extractors = {name: _extractor(name, config) for name in config.extractors}
    return ShardAttrs(
        toolkit_version=__version__,
        joint_names=tuple(JOINT_NAMES),
        icosahedron_template=TEMPLATE,
        icosahedron_radius=config.icosahedron_radius,
        shell_vertex_ids=np.asarray(body.shell_ids, dtype=np.int64),
        body_model_name=Path(body_model_path).stem,
        body_model_sha256=body_model_sha,
        extractors={name: {"dim": e.dim, **jsonable(e.record())} for name, e in extractors.items()},
    )


def jsonable(value):
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def process_pair(pair: PairRecord, body_model_path: str, config: PrepConfig
                 ) -> tuple[dict[str, np.ndarray], list[str], dict[str, int]]:
    """Both persons' arrays for one dyad, keyed "<person>/<name>", the loader's warnings and the
    count of frames with non-finite parameters (``PersonArrays.nonfinite``, summed).

    Raises DataProblem for bad input.
    """
    from .speaking import frame_energy_db, labels_from_levels

    people = [load_person(pair, person) for person in pair.persons]
    if any(p.audio is None for p in people):
        raise DataProblem(pair.folder / pair.sequence, "no audio")
    levels = [frame_energy_db(p.audio) for p in people]
    body = _body_model(body_model_path, config)
    posed = [body.forward(p.params, batch_frames=config.body_batch_frames) for p in people]
    heads = [gaze.head_trajectory(b.eye_mid) for b in posed]
    arrays: dict[str, np.ndarray] = {}
    warnings = [w for p in people for w in p.warnings]
    for i, (person, arrays_in, frames_out) in enumerate(zip(pair.persons, people, posed)):
        partner = 1 - i
        prefix = f"{person}/"
        arrays[prefix + "icosahedra"] = icosahedron.encode(
            frames_out.joints, frames_out.rotations, config.icosahedron_radius).astype(np.float32, copy=False)
        arrays[prefix + "shell"] = frames_out.shell.astype(np.float32, copy=False)
        arrays[prefix + "head"] = heads[i].astype(np.float32)
        arrays[prefix + "gaze"] = gaze.gaze_score(frames_out.head_front, frames_out.head_back,
                                                  heads[partner]).astype(np.float32)
        speaking = labels_from_levels(levels[i], levels[partner], config.speaking)
        arrays[prefix + "speaking"] = np.pad(speaking, (0, max(0, pair.length - speaking.size)))[: pair.length].astype(np.uint8)
        arrays[prefix + "valid"] = arrays_in.valid.astype(np.uint8)
        arrays[prefix + "root_position"] = frames_out.joints[:, JOINT["pelvis"]].astype(np.float32)
        arrays[prefix + "root_rotation"] = frames_out.rotations[:, JOINT["pelvis"]].astype(np.float32)
        betas, varies = person_betas(arrays_in.params["betas"], arrays_in.valid)
        betas = body.shape_betas(betas)  # one row padded or cut to the model's count
        if varies:
            warnings.append(f"{pair.sequence}/{person}: betas vary over frames (up to {varies:.3g}); "
                            f"the shards keep their median for export")
        arrays[prefix + "betas"] = betas.astype(np.float32)
        arrays[prefix + "rest_joints"] = body.rest_joints(betas).astype(np.float32)
        for name in config.extractors:
            arrays[prefix + f"audio/{name}"] = _extractor(name, config).extract(
                arrays_in.audio, pair.length).astype(np.float32, copy=False)
    nonfinite = {key: sum(p.nonfinite[key] for p in people) for key in ("tracked", "untracked")}
    return arrays, warnings, nonfinite


def person_betas(betas: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, float]:
    """One body shape for a person: the betas of the tracked frames when they agree (the usual
    case: one fit per capture), else their median, with the largest deviation from it (0.0 when
    they agree)."""
    betas = np.atleast_2d(betas)
    rows = betas[np.asarray(valid, bool)] if np.any(valid) else betas
    if bool((rows == rows[:1]).all()):
        return rows[0].copy(), 0.0
    median = np.median(rows, axis=0)
    return median, float(np.abs(rows - median).max())


def fingerprint(pair: PairRecord, split: str, body_model_sha: str, config: PrepConfig) -> str:
    """Identifies a work file's inputs: a resumed run reuses a work file only on a match."""
    stats = [(str(p), os.stat(p).st_size, os.stat(p).st_mtime_ns) for person in pair.persons
             for p in pair.files[person].paths() if p.exists()]
    payload = json.dumps([WORK_FORMAT, __version__, pair.sequence, split, body_model_sha, asdict(config),
                          stats], sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()


def run_task(pair: PairRecord, split: str, body_model_path: str, body_model_sha: str,
             config: PrepConfig, work_dir: str) -> TaskResult:
    """Process one dyad into `<work_dir>/<sequence>.h5` (+ `.json`, written last as the marker)."""
    torch.set_num_threads(1)  # one thread per task: results do not depend on -j (byte-identical shards)
    start = time.perf_counter()
    result = TaskResult(pair.sequence, "ok", frames=pair.length)
    try:
        result.sources = [{"path": str(p), "bytes": p.stat().st_size, "sha256": file_sha256(p)}
                          for person in pair.persons for p in pair.files[person].paths()
                          if p.exists()]
        arrays, result.warnings, result.nonfinite = process_pair(pair, body_model_path, config)
        gender = _body_model(body_model_path, config).gender
        seq = ProcessedSequence.from_arrays(pair.sequence, session=pair.session, split=split,
                                            persons=list(pair.persons), arrays=arrays,
                                            genders={person: gender for person in pair.persons})
        write_work_file(Path(work_dir) / f"{pair.sequence}.h5", seq,
                        shard_attrs(body_model_path, body_model_sha, config))
    except DataProblem as problem:
        result.status, result.reason = "skipped", str(problem)
    except Exception as error:  # noqa: BLE001 - a bug must not stop a long run; it is reported
        if out_of_space(error):
            raise OutOfSpace(f"{work_dir}: no space left on the device (writing {pair.sequence})") from None
        result.status = "failed"
        # One line (HDF5's messages span several); the traceback goes to report.json.
        result.reason = f"{pair.sequence}: unexpected {type(error).__name__}: {' '.join(str(error).split())}"
        result.detail = traceback.format_exc()
    result_seconds = time.perf_counter() - start
    marker = {**asdict(result), "fingerprint": fingerprint(pair, split, body_model_sha, config),
              "wall_seconds": result_seconds}
    atomic_write_bytes(Path(work_dir) / f"{pair.sequence}.json", json.dumps(marker, sort_keys=True).encode(),
                       durable=True)
    return result


def write_work_file(path: Path, seq: ProcessedSequence, attrs: ShardAttrs) -> None:
    """A shard file holding `seq` alone, and for a train sequence its statistics moments."""
    from .stats import STATS_SPLIT, sequence_moments, write_moments

    with atomic_h5(path) as handle:
        attrs.write(handle.attrs, seq.split)
        stored = write_sequence(handle, seq, attrs)
        if seq.split == STATS_SPLIT:
            persons = [{**arrays, "audio": {k[len("audio/"):]: v for k, v in arrays.items()
                                            if k.startswith("audio/")}} for _, arrays in stored]
            write_moments(create_group(handle, MOMENTS_GROUP),
                          sequence_moments(persons, sorted(attrs.extractors),
                                           joint_names=attrs.joint_names))
