"""Checking and summarizing a shards folder: `sarah-prep --verify` and `sarah-prep --info`.

Verification reads everything back (so HDF5's fletcher32 checksums are exercised) and compares
the files with the manifest; the summary is the table `--info` prints.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from sarah_data.constants import READABLE_SCHEMA_VERSIONS
from sarah_data.shards import (MANIFEST_NAME, PERSON_DATASETS, SEQUENCE_ATTRS, SHARD_FILE_RE, ShardAttrs,
                               ShardError, ShardSet, file_sha256, read_manifest)
from sarah_data.splits import SPLITS


# --------------------------------------------------------------------------- verification

def verify_shards(shards_dir: Path | str, body_model: Path | str | None = None) -> list[str]:
    """Check a shards folder end to end; returns one line per problem (empty when all is well).

    Checks: the manifest parses and has this toolkit's schema version; every listed file exists
    with the recorded size and sha256, and no unlisted shard file is present; every dataset of
    every file reads back (HDF5 fletcher32 checksums); root attributes are complete, of this
    schema version and the same in every file; each sequence has its attributes and all required
    datasets with consistent shapes; the sequences in each file, their split, persons and frame
    counts match the manifest. With ``body_model``, that file is the one the shards were made
    with (its sha256 against the manifest's and the files' records).
    """
    root = Path(shards_dir)
    try:
        manifest = read_manifest(root / MANIFEST_NAME)
    except ShardError as error:
        return [str(error)]
    problems: list[str] = []
    if body_model is not None:
        problems += _check_body_model(Path(body_model), manifest.config.get("body_model", {}))
    if manifest.schema_version not in READABLE_SCHEMA_VERSIONS:
        problems.append(f"{MANIFEST_NAME}: schema version {manifest.schema_version}, "
                        f"expected one of {READABLE_SCHEMA_VERSIONS}")
    listed = {info.file for info in manifest.shards}
    for path in sorted(root.iterdir()):
        if SHARD_FILE_RE.match(path.name) and path.name not in listed:
            problems.append(f"{path.name}: shard file not listed in {MANIFEST_NAME}")
    in_files: dict[str, str] = {}
    reference_attrs: dict | None = None
    for info in sorted(manifest.shards, key=lambda s: s.file):
        path = root / info.file
        if not path.is_file():
            problems.append(f"{info.file}: missing")
            continue
        size = path.stat().st_size
        if size != info.bytes:
            problems.append(f"{info.file}: size {size} bytes, manifest says {info.bytes}")
        if file_sha256(path) != info.sha256:
            problems.append(f"{info.file}: sha256 differs from the manifest")
        file_problems, sequences, attrs = _verify_file(path, info.split)
        problems += [f"{info.file}: {p}" for p in file_problems]
        if attrs is not None:
            if reference_attrs is None:
                reference_attrs = attrs
            elif attrs != reference_attrs:
                problems.append(f"{info.file}: root attributes differ from the other shard files")
        if sequences is not None and list(sequences) != sorted(info.sequences):
            problems.append(f"{info.file}: holds sequences {sorted(sequences)}, manifest lists "
                            f"{sorted(info.sequences)}")
        for name, (split, persons, frames) in (sequences or {}).items():
            in_files[name] = info.file
            entry = manifest.sequences.get(name)
            if entry is None:
                problems.append(f"{info.file}: sequence {name} is not in the manifest's sequences")
                continue
            if entry.file != info.file:
                problems.append(f"{MANIFEST_NAME}: sequence {name} is in {info.file}, "
                                f"manifest says {entry.file}")
            if (entry.split, tuple(entry.persons), entry.frames) != (split, persons, frames):
                problems.append(f"{info.file}: sequence {name} has split/persons/frames "
                                f"{(split, list(persons), frames)}, manifest says "
                                f"{(entry.split, list(entry.persons), entry.frames)}")
    for name in sorted(set(manifest.sequences) - set(in_files)):
        problems.append(f"{MANIFEST_NAME}: sequence {name} is in no shard file")
    return problems


def _verify_file(path: Path, split: str) -> tuple[list[str], dict | None, dict | None]:
    """Problems, {sequence: (split, persons, frames)} and the root attributes of one file."""
    problems: list[str] = []
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        return [f"not a readable HDF5 file ({error})"], None, None
    with handle:
        try:
            attrs = ShardAttrs.read(handle.attrs, path)
        except ShardError as error:
            return [error.reason], None, None
        if attrs.schema_version not in READABLE_SCHEMA_VERSIONS:
            problems.append(f"schema version {attrs.schema_version}, expected one of "
                            f"{READABLE_SCHEMA_VERSIONS}")
        if str(handle.attrs["split"]) != split:
            problems.append(f"root split {handle.attrs['split']!r}, manifest says {split!r}")
        sequences = {}
        for name in handle:
            seq_problems, summary = _verify_sequence(handle[name], attrs)
            problems += [f"{name}: {p}" for p in seq_problems]
            if summary is not None:
                sequences[name] = summary
    return problems, sequences, attrs.to_json()


def _verify_sequence(group, attrs: ShardAttrs) -> tuple[list[str], tuple | None]:
    if not isinstance(group, h5py.Group):
        return ["expected a sequence group"], None
    missing = [a for a in SEQUENCE_ATTRS if a not in group.attrs]
    if missing:
        return [f"missing attributes {missing}"], None
    frames = int(group.attrs["frames"])
    persons = tuple(str(p) for p in group.attrs["persons"])
    problems = []
    if int(group.attrs["fps"]) != attrs.fps:
        problems.append(f"fps {int(group.attrs['fps'])} differs from the root fps {attrs.fps}")
    if sorted(persons) != sorted(group) or len(persons) != 2:
        problems.append(f"persons attribute {list(persons)} does not match groups {sorted(group)}")
    sizes = {"J": len(attrs.joint_names), "V": len(attrs.shell_vertex_ids)}
    audio_dims = []
    for person in persons:
        if person not in group:
            continue
        g = group[person]
        for name, (dtype, tail) in PERSON_DATASETS.items():
            expected = (frames,) + tuple(sizes.get(d, d) for d in tail)
            problems += _check_dataset(g, name, expected, dtype, person)
        dims = {}
        for extractor in (g["audio"] if "audio" in g else ()):
            if extractor not in attrs.extractors:
                problems.append(f"{person}/audio/{extractor}: extractor not in root attributes")
            dset = g["audio"][extractor]
            if not isinstance(dset, h5py.Dataset) or dset.ndim != 2:
                problems.append(f"{person}/audio/{extractor}: expected a (T, D) dataset")
                continue
            dims[extractor] = dset.shape[1]
            problems += _check_dataset(g["audio"], extractor, (frames, dset.shape[1]),
                                       np.float32, f"{person}/audio")
        audio_dims.append(dims)
    if len(audio_dims) == 2 and audio_dims[0] != audio_dims[1]:
        problems.append(f"persons have different audio features {audio_dims}")
    return problems, (str(group.attrs["split"]), persons, frames)


def _check_dataset(group: h5py.Group, name: str, shape: tuple, dtype, where: str) -> list[str]:
    if name not in group or not isinstance(group[name], h5py.Dataset):
        return [f"{where}/{name}: missing"]
    dset = group[name]
    problems = []
    if dset.shape != shape:
        problems.append(f"{where}/{name}: shape {dset.shape}, expected {shape}")
    if dset.dtype != np.dtype(dtype):
        problems.append(f"{where}/{name}: dtype {dset.dtype}, expected {np.dtype(dtype)}")
    try:
        dset[()]  # decompresses every chunk: a fletcher32 mismatch raises here
    except OSError as error:
        problems.append(f"{where}/{name}: unreadable ({error})")
    return problems


# --------------------------------------------------------------------------- summary

def summarize(shards_dir: Path | str) -> list[dict]:
    """One row per split plus a total row, for `sarah-prep --info`.

    Columns: split, files, bytes, sequences, sessions, hours (all frames), tracked_hours (frames
    where both persons are tracked, the frames training windows come from), speaking (fraction of
    tracked person-frames labelled speaking), and one `<extractor> hours` column per audio feature
    (hours of sequences that have it).
    """
    shards = ShardSet(shards_dir)
    try:
        extractors = sorted(shards.attrs.extractors) if shards.manifest.shards else []
        splits = [s for s in SPLITS if shards.sequences(s)]
        splits += sorted({e.split for e in shards.manifest.sequences.values()} - set(splits))
        rows = []
        for split in splits + [None]:
            names = shards.sequences(split)
            row = {"split": split or "total",
                   "files": sum(1 for s in shards.manifest.shards if split in (None, s.split)),
                   "bytes": sum(s.bytes for s in shards.manifest.shards if split in (None, s.split)),
                   "sequences": len(names),
                   "sessions": len({shards.entry(n).session for n in names})}
            seconds = tracked = speaking = 0.0
            feature_seconds = dict.fromkeys(extractors, 0.0)
            for name in names:
                group = shards.group(name)
                fps = int(group.attrs["fps"])
                persons = [group[p] for p in group.attrs["persons"]]
                both = np.logical_and(*(p["valid"][()].astype(bool) for p in persons))
                seconds += int(group.attrs["frames"]) / fps
                tracked += both.sum() / fps
                speaking += sum(p["speaking"][()].astype(bool)[both].sum() for p in persons) / fps
                for extractor in extractors:
                    if "audio" in persons[0] and extractor in persons[0]["audio"]:
                        feature_seconds[extractor] += int(group.attrs["frames"]) / fps
            row["hours"] = seconds / 3600
            row["tracked_hours"] = tracked / 3600
            row["speaking"] = speaking / (2 * tracked) if tracked else 0.0
            for extractor in extractors:
                row[f"{extractor} hours"] = feature_seconds[extractor] / 3600
            rows.append(row)
        return rows
    finally:
        shards.close()


def format_summary(rows: list[dict]) -> str:
    """The summary rows as an aligned text table."""
    if not rows:
        return "(no sequences)"
    columns = list(rows[0])

    def cell(value) -> str:
        if isinstance(value, float):
            return f"{value:.3f}"
        if isinstance(value, int) and not isinstance(value, bool):
            return f"{value:,}"
        return str(value)

    table = [columns] + [[cell(row[c]) for c in columns] for row in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(columns))]
    return "\n".join("  ".join(text.rjust(w) if i else text.ljust(w)
                               for i, (text, w) in enumerate(zip(line, widths))) for line in table)


def _check_body_model(path: Path, recorded: dict) -> list[str]:
    if not path.is_file():
        return [f"--body-model {path}: no such file"]
    sha = file_sha256(path)
    if recorded.get("sha256") != sha:
        return [f"body model {path} (sha256 {sha[:12]}...) is not the one these shards were made "
                f"with ({recorded.get('name')}, sha256 {str(recorded.get('sha256'))[:12]}...)"]
    return []
