"""`sarah-prep raw/ shards/`: raw Embody 3D sections in, HDF5 shards out.

    read the corpus -> split sessions -> process each dyad (any executor) into a work file
    -> assemble shards per split in sorted order -> train statistics -> manifest, report

Work files (`shards/.work/<sequence>.h5`, a compressed one-sequence shard written by the task,
and a `.json` marker written after it) make a killed run resumable: a rerun keeps every sequence
whose marker matches its inputs and redoes the rest. Shards are assembled from work files in
corpus order while the tasks run (assemble.py), by copying their compressed chunks: nothing is
decoded or compressed again in this process, and `-j 1`, `-j 8` and a resumed run write identical
bytes. The train statistics are merged from the moments each task stored. The work folder is
removed once the manifest is written.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from concurrent.futures import Executor, as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from . import __version__
from .config import PrepConfig
from .constants import FPS
from .embody3d import PairRecord, read_corpus
from .executors import make_executor
from .assemble import Assembler
from .process import TaskResult, fingerprint, jsonable, run_task
from .atomic import atomic_write_bytes
from .shards import file_sha256
from .splits import SPLITS, session_frames_of, split_sessions

BODY_MODEL_ENV = "SARAH_BODY_MODEL"
BODY_MODEL_FOLDER = "body_models"


class PrepError(Exception):
    """A problem that stops the whole run (as opposed to one bad sequence): one clear line."""


@dataclass
class PrepResult:
    written: list[str] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)  # {"path"/"sequence", "reason", "kind"}
    shards: list[dict] = field(default_factory=list)
    hours: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0

    @property
    def dyad_seconds(self) -> float:
        return sum(self.hours.values()) * 3600.0


def find_sections(inputs: list[Path], only: list[str] | None = None) -> list[Path]:
    """Section folders (holding a dataset.json) among the inputs and their direct subfolders;
    with ``only``, those of these folder names (PrepError naming any that is not there)."""
    sections = []
    for folder in inputs:
        folder = Path(folder)
        if not folder.is_dir():
            raise PrepError(f"{folder}: not a folder")
        if (folder / "dataset.json").exists():
            sections.append(folder)
        sections += sorted(p.parent for p in folder.glob("*/dataset.json"))
    if not sections:
        raise PrepError(f"{', '.join(map(str, inputs))}: no dataset.json found (expected an Embody 3D "
                        "section folder such as raw/aiagent/ with its dataset.json, or its parent)")
    if only:
        names = {p.name for p in sections}
        missing = [name for name in only if name not in names]
        if missing:
            raise PrepError(f"--sections {', '.join(missing)}: not found; the inputs hold "
                            f"{', '.join(sorted(names))}")
        sections = [p for p in sections if p.name in only]
    return sections


def check_same_body_model(out_dir: Path, model_path: Path, model_sha: str) -> None:
    """A run into a folder that already holds shards must use the body model they were made with
    (its sha256 is in their manifest): mixing two bodies in one corpus would go unnoticed."""
    manifest = Path(out_dir) / "manifest.json"
    if not manifest.is_file():
        return
    try:
        recorded = json.loads(manifest.read_text())["config"]["body_model"]
    except (OSError, ValueError, KeyError, TypeError):
        return  # not ours or unreadable: the run rewrites it
    if recorded.get("sha256") != model_sha:
        raise PrepError(f"{out_dir} holds shards made with body model {recorded.get('name')} "
                        f"(sha256 {str(recorded.get('sha256'))[:12]}...), this run uses {model_path} "
                        f"(sha256 {model_sha[:12]}...): use a new output folder, or that model")


def resolve_body_model(inputs: list[Path], explicit: str | None) -> Path:
    """--body-model, else the one model file under <input>/body_models/, else $SARAH_BODY_MODEL."""
    if explicit:
        path = Path(explicit)
        if not path.is_file():
            raise PrepError(f"{path}: body model file not found")
        return path
    found = sorted({p for folder in inputs for p in Path(folder).glob(f"{BODY_MODEL_FOLDER}/*.npz")})
    if not found:
        # The Embody 3D loader's layout: body_models/smplx_models_lockedhead/smplx/SMPLX_*.npz
        # (the locked-head SMPL-X release); the neutral model when several genders are there.
        nested = sorted({p for folder in inputs for p in Path(folder).glob(f"{BODY_MODEL_FOLDER}/**/*.npz")})
        neutral = [p for p in nested if "neutral" in p.name.lower()]
        found = neutral if len(neutral) == 1 else nested
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise PrepError(f"several body model files ({', '.join(map(str, found))}): choose one with --body-model")
    if os.environ.get(BODY_MODEL_ENV):
        return resolve_body_model(inputs, os.environ[BODY_MODEL_ENV])
    raise PrepError(
        "no body model: pass --body-model PATH (your licensed SMPL-X file, e.g. SMPLX_NEUTRAL.npz), "
        f"put one .npz under {inputs[0]}/{BODY_MODEL_FOLDER}/, or set ${BODY_MODEL_ENV} "
        "(sarah-fixtures writes a procedural body model there)")


def prepare(inputs: list[Path] | Path, out_dir: Path, config: PrepConfig = PrepConfig(), *,
            body_model: str | None = None, jobs: int = 1, executor: str | Executor = "process",
            ray_address: str | None = None, progress: bool = True, log=print,
            sections: list[str] | None = None) -> PrepResult:
    """Run the whole pipeline; bad sequences are reported and skipped, never fatal."""
    from .shards import Manifest, SourceFile, write_manifest
    from .stats import merge_moments, write_stats

    problems = config.problems()
    if problems:  # before any work: a bad setting used to surface per sequence, at the end
        raise PrepError("; ".join(problems))
    started = time.perf_counter()
    inputs = [Path(p) for p in ([inputs] if isinstance(inputs, (str, Path)) else inputs)]
    out_dir = Path(out_dir)
    section_dirs = find_sections(inputs, sections)
    model_path = resolve_body_model(inputs, body_model)
    model_sha = file_sha256(model_path)
    check_same_body_model(out_dir, model_path, model_sha)
    corpus = read_corpus(section_dirs)
    result = PrepResult()
    section_of = _section_namer(section_dirs)
    for problem in corpus.problems:
        _skip(result, log, {"path": str(problem.path), "reason": problem.reason, "kind": "unreadable",
                            "section": section_of(problem.path)})
    for skip in corpus.skipped:
        _skip(result, log, {"sequence": skip.sequence, "path": str(skip.path), "reason": skip.reason,
                            "kind": skip.kind, "section": section_of(skip.path)})
    notes = [note for pair in corpus.pairs for note in pair.notes]
    for note in notes:
        log(f"note: {note}")

    splits = split_sessions(session_frames_of(corpus.pairs), config.split_fractions, config.split_seed)
    split_of = {session: name for name, sessions in splits.items() for session in sessions}
    out_dir.mkdir(parents=True, exist_ok=True)
    work_dir = out_dir / ".work"
    work_dir.mkdir(exist_ok=True)
    _remove_temporaries(out_dir)

    assembler = Assembler(out_dir, work_dir, corpus.pairs, split_of, config)
    try:
        results = _run_tasks(corpus.pairs, split_of, model_path, model_sha, config, work_dir, jobs,
                             executor, ray_address, progress, assembler.update)
        shards, entries = assembler.close()
    except BaseException:
        assembler.abort()
        raise
    done: dict[str, list[PairRecord]] = {name: [] for name in SPLITS}
    sources: dict[str, list[dict]] = {}
    for pair in corpus.pairs:
        task = results[pair.sequence]
        for warning in task.warnings:
            log(f"warning: {warning}")
        if task.status == "ok":
            done[split_of[pair.session]].append(pair)
            sources[pair.sequence] = task.sources
        else:
            kind = "no-audio" if task.reason.endswith(": no audio") else task.status
            _skip(result, log, {"sequence": pair.sequence, "reason": task.reason, "kind": kind,
                                "section": section_of(pair.folder),
                                **({"traceback": task.detail} if task.detail else {})})
    for line in skip_summary(result.skipped):
        log(line)

    result.shards = [asdict(info) for info in shards]
    result.written = [p.sequence for name in SPLITS for p in done[name]]
    result.hours = {name: sum(p.length for p in done[name]) / FPS / 3600 for name in SPLITS}
    sequences = {seq: replace(entry, sources=tuple(SourceFile(**d) for d in sources[seq]))
                 for seq, entry in sorted(entries.items())}
    run_config = {**jsonable(asdict(config)), "body_model": {"name": model_path.stem, "sha256": model_sha}}
    write_manifest(out_dir / "manifest.json", Manifest(__version__, run_config, splits, shards, sequences))
    if result.written:
        # the same numbers compute_stats(out_dir) gets from the shards, without reading them
        moments = assembler.moments
        write_stats(out_dir, merge_moments([moments[name] for name in sorted(moments)],
                                           sorted(assembler.attrs.extractors)), len(moments))
    nonfinite = {seq: task.nonfinite for seq, task in sorted(results.items())
                 if task.status == "ok" and any(task.nonfinite.values())}
    report = {"written": len(result.written), "skipped": result.skipped,
              "skipped_counts": skip_counts(result.skipped), "notes": notes,
              "nonfinite_frames": {"tracked_marked_untracked": sum(n["tracked"] for n in nonfinite.values()),
                                   "untracked": sum(n["untracked"] for n in nonfinite.values()),
                                   "sequences": nonfinite}}
    atomic_write_bytes(out_dir / "report.json", (json.dumps(report, indent=2, sort_keys=True) + "\n").encode(),
                       durable=True)
    shutil.rmtree(work_dir, ignore_errors=True)
    result.wall_seconds = time.perf_counter() - started
    return result


def _run_tasks(pairs, split_of, model_path, model_sha, config, work_dir, jobs, executor, ray_address,
               progress, on_result) -> dict[str, TaskResult]:
    """Every pair's result (reused from a matching work file, or computed); `on_result(results)`
    after each one arrives."""
    results: dict[str, TaskResult] = {}
    todo = []
    for pair in pairs:
        reused = _reusable(work_dir, pair, split_of[pair.session], model_sha, config)
        if reused is not None:
            results[pair.sequence] = reused
        else:
            todo.append(pair)
    on_result(results)
    own_executor = not isinstance(executor, Executor)
    pool = make_executor(executor, jobs, ray_address) if own_executor else executor
    total = sum(p.length for p in pairs) / FPS
    bar = tqdm(total=round(total), unit="dyad-s", desc="sarah-prep", disable=not progress,
               initial=round(sum(p.length for p in pairs if p.sequence in results) / FPS), file=sys.stderr)
    try:
        futures = {pool.submit(run_task, pair, split_of[pair.session], str(model_path), model_sha,
                               config, str(work_dir)): pair
                   for pair in todo}
        for future in as_completed(futures):
            pair = futures[future]
            results[pair.sequence] = future.result()
            on_result(results)
            bar.update(round(pair.length / FPS))
    except BaseException:
        if own_executor:  # a full disk or Ctrl-C: queued tasks would only fail the same way
            pool.shutdown(cancel_futures=True)
        raise
    else:
        if own_executor:
            pool.shutdown()
    finally:
        bar.close()
    return results


def _reusable(work_dir: Path, pair: PairRecord, split: str, model_sha: str, config: PrepConfig
              ) -> TaskResult | None:
    marker = work_dir / f"{pair.sequence}.json"
    if not marker.exists():
        return None
    try:
        saved = json.loads(marker.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if saved.get("fingerprint") != fingerprint(pair, split, model_sha, config):
        return None
    if saved["status"] == "ok" and not (work_dir / f"{pair.sequence}.h5").exists():
        return None
    fields = TaskResult.__dataclass_fields__
    return TaskResult(**{k: v for k, v in saved.items() if k in fields})


SKIP_LINES = 20  # skipped inputs named one per line; past this, counts (report.json has them all)


def _section_namer(section_dirs: list[Path]):
    resolved = [(d.resolve(), d.name) for d in section_dirs]

    def section_of(path) -> str:
        path = Path(path).resolve()
        for folder, name in resolved:
            if path == folder or folder in path.parents:
                return name
        return ""

    return section_of


def _skip(result: PrepResult, log, entry: dict) -> None:
    result.skipped.append(entry)
    if entry["kind"] == "no-audio":
        return  # expected in Embody 3D: counted in the summary, not a line each
    shown = sum(1 for e in result.skipped if e["kind"] != "no-audio")
    if shown > SKIP_LINES:
        return
    where = entry.get("sequence") or entry.get("path")
    reason = entry["reason"]
    log(f"skipped: {reason}" if where and str(where) in reason else f"skipped: {where}: {reason}")
    if shown == SKIP_LINES:
        log("(further skipped inputs are counted below; report.json lists every one)")


def skip_counts(skipped: list[dict]) -> dict[str, dict[str, int]]:
    """Skipped inputs counted by kind and by section (sorted, for the report)."""
    by_kind: dict[str, int] = {}
    by_section: dict[str, int] = {}
    for entry in skipped:
        by_kind[entry["kind"]] = by_kind.get(entry["kind"], 0) + 1
        section = entry.get("section") or "(no section)"
        by_section[section] = by_section.get(section, 0) + 1
    return {"by_kind": dict(sorted(by_kind.items())), "by_section": dict(sorted(by_section.items()))}


def skip_summary(skipped: list[dict]) -> list[str]:
    """The lines that end a run's report of what it left out."""
    if not skipped:
        return []
    counts = skip_counts(skipped)
    lines = []
    no_audio = counts["by_kind"].get("no-audio", 0)
    if no_audio:
        lines.append(f"note: {no_audio} sequence{'s' if no_audio > 1 else ''} without audio left out "
                     f"(Embody 3D has such captures; the model needs both voices)")
    others = skip_counts([e for e in skipped if e["kind"] != "no-audio"])
    if others["by_kind"]:
        lines.append(f"skipped {sum(others['by_kind'].values())} inputs by reason: "
                     + ", ".join(f"{k} {v}" for k, v in others["by_kind"].items())
                     + "; by section: " + ", ".join(f"{k} {v}" for k, v in others["by_section"].items())
                     + " (report.json lists each)")
    return lines


def _remove_temporaries(out_dir: Path) -> None:
    for path in list(out_dir.glob(".*.tmp-*")) + list((out_dir / ".work").glob(".*.tmp-*")):
        path.unlink(missing_ok=True)
