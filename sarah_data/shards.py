"""The shard format: processed dyadic sequences in HDF5 files, written atomically and reproducibly.

A shards folder holds `<split>-NNNNN.h5` files (each at most `max_bytes`, a sequence never split
across files), `manifest.json` (the index: written by prep with `write_manifest`) and `stats.h5`
(sarah_data/stats.py). The layout is documented in docs/shard-format.md; this module is its only
writer and the reference reader.

Reproducibility: the same sequences with the same attributes, added in the same order, give
byte-identical files. HDF5 stores object timestamps by default; every group and dataset here is
created with time tracking off and the file format pinned (`libver` bounds), so nothing in a file
depends on when or where it was written.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import h5py
import numpy as np

from sarah_data.chunks import LEVEL as COMPRESSION_LEVEL
from sarah_data.chunks import write_chunks
from sarah_data.constants import FPS, SHARD_SCHEMA_VERSION
from sarah_data.loading import DataProblem
from sarah_data.splits import SPLITS

MANIFEST_NAME = "manifest.json"
STATS_NAME = "stats.h5"
DEFAULT_MAX_BYTES = 1 << 30  # 1 GiB per shard file
CHUNK_FRAMES = 100  # a random 400-frame window decompresses at most 500 frames per dataset
# Group headers, attributes and chunk indices a sequence adds beyond its array bytes; part of the
# size estimate that decides when to start a new file.
SEQUENCE_OVERHEAD_BYTES = 64 * 1024
SHARD_FILE_RE = re.compile(r"^(?P<split>[a-z]+)-(?P<index>\d{5})\.h5$")

# Per-person datasets: name -> (stored dtype, shape after the time axis; "J" and "V" stand for the
# joint and shell point counts of the root attributes).
PERSON_DATASETS = {
    "icosahedra": (np.float32, ("J", 12, 3)),
    "shell": (np.float32, ("V", 3)),
    "head": (np.float32, (2,)),
    "gaze": (np.float32, ()),
    "speaking": (np.uint8, ()),
    "valid": (np.uint8, ()),
    "root_position": (np.float32, (3,)),
    "root_rotation": (np.float32, (3, 3)),
}
ROOT_ATTRS = ("schema_version", "toolkit_version", "split", "fps", "joint_names",
              "icosahedron_template", "icosahedron_radius", "shell_vertex_ids",
              "body_model_name", "body_model_sha256", "extractors")
SEQUENCE_ATTRS = ("session", "split", "frames", "fps", "persons")


class ShardError(DataProblem):
    """A shard, manifest or sequence that cannot be written or read: `path` and `reason`."""


def shard_name(split: str, index: int) -> str:
    return f"{split}-{index:05d}.h5"


# --------------------------------------------------------------------------- in-memory records

@dataclass
class ProcessedPerson:
    """One person of a processed sequence, world coordinates (y up, metres), T frames at 30 fps.

    `speaking` and `valid` are boolean (stored as uint8 0/1); `audio` maps an extractor name to
    its (T, D) features. Every float array must be finite, including at untracked frames.
    """

    name: str
    icosahedra: np.ndarray  # (T, J, 12, 3)
    shell: np.ndarray  # (T, V, 3)
    head: np.ndarray  # (T, 2) floor-projected eye midpoint (x, z)
    gaze: np.ndarray  # (T,) this person's gaze score toward the partner
    speaking: np.ndarray  # (T,)
    valid: np.ndarray  # (T,) tracking mask
    root_position: np.ndarray  # (T, 3) pelvis
    root_rotation: np.ndarray  # (T, 3, 3) pelvis global rotation
    audio: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return int(np.shape(self.valid)[0])


@dataclass
class ProcessedSequence:
    """Both persons of one dyadic sequence, as prep hands it to `ShardWriter.add`."""

    name: str
    session: str
    split: str
    persons: tuple[ProcessedPerson, ProcessedPerson]
    fps: int = FPS

    @property
    def frames(self) -> int:
        return self.persons[0].frames

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat `{"<person>/<dataset>": array, "<person>/audio/<extractor>": array}` (e.g. for npz)."""
        arrays = {}
        for person in self.persons:
            for key in PERSON_DATASETS:
                arrays[f"{person.name}/{key}"] = np.asarray(getattr(person, key))
            for extractor, features in person.audio.items():
                arrays[f"{person.name}/audio/{extractor}"] = np.asarray(features)
        return arrays

    @classmethod
    def from_arrays(cls, name: str, session: str, split: str, persons: list[str],
                    arrays: Mapping[str, np.ndarray], fps: int = FPS) -> "ProcessedSequence":
        """The inverse of `to_arrays`, given the two person names in order."""
        where = f"sequence {name}"
        expected = {f"{p}/{key}" for p in persons for key in PERSON_DATASETS}
        missing = sorted(expected - set(arrays))
        audio_keys = {k for k in arrays if any(k.startswith(f"{p}/audio/") for p in persons)}
        unknown = sorted(set(arrays) - expected - audio_keys)
        if missing or unknown:
            raise ShardError(where, f"arrays missing {missing}, unexpected {unknown}")
        people = []
        for person in persons:
            values = {key: arrays[f"{person}/{key}"] for key in PERSON_DATASETS}
            values["speaking"] = np.asarray(values["speaking"]).astype(bool)
            values["valid"] = np.asarray(values["valid"]).astype(bool)
            prefix = f"{person}/audio/"
            audio = {k[len(prefix):]: arrays[k] for k in sorted(audio_keys) if k.startswith(prefix)}
            people.append(ProcessedPerson(name=person, audio=audio, **values))
        return cls(name=name, session=session, split=split, persons=tuple(people), fps=fps)


@dataclass
class ShardAttrs:
    """The root attributes every shard file of one prep run shares."""

    toolkit_version: str
    joint_names: tuple[str, ...]
    icosahedron_template: np.ndarray  # (12, 3) unit icosahedron, vertex order of the encoding
    icosahedron_radius: float
    shell_vertex_ids: np.ndarray  # (V,) mesh vertex index of each shell point
    body_model_name: str
    body_model_sha256: str
    extractors: dict[str, dict] = field(default_factory=dict)  # name -> config (JSON-able)
    fps: int = FPS
    schema_version: int = SHARD_SCHEMA_VERSION

    @classmethod
    def coerce(cls, attrs: "ShardAttrs | Mapping") -> "ShardAttrs":
        """`attrs` itself, or a ShardAttrs from a mapping with the same field names; checked."""
        if not isinstance(attrs, ShardAttrs):
            unknown = sorted(set(attrs) - set(cls.__dataclass_fields__))
            if unknown:
                raise ValueError(f"unknown shard root attributes {unknown}")
            attrs = cls(**attrs)
        template = np.asarray(attrs.icosahedron_template, np.float64)
        if template.shape != (12, 3) or not np.allclose(np.linalg.norm(template, axis=1), 1, atol=1e-6):
            raise ValueError("icosahedron_template must be the unit icosahedron (12, 3) "
                             "(icosahedron.TEMPLATE); the radius is a separate attribute")
        if attrs.schema_version != SHARD_SCHEMA_VERSION:
            raise ValueError(f"schema_version {attrs.schema_version}: this toolkit writes "
                             f"{SHARD_SCHEMA_VERSION}")
        if np.asarray(attrs.shell_vertex_ids).ndim != 1 or not attrs.joint_names:
            raise ValueError("joint_names must be non-empty and shell_vertex_ids one-dimensional")
        return attrs

    def to_json(self) -> dict:
        """Plain-JSON form (arrays as lists), for comparison and reports."""
        data = asdict(self)
        data["joint_names"] = list(self.joint_names)
        data["icosahedron_template"] = np.asarray(self.icosahedron_template, np.float64).tolist()
        data["shell_vertex_ids"] = np.asarray(self.shell_vertex_ids, np.int64).tolist()
        return data

    def write(self, attrs: h5py.AttributeManager, split: str) -> None:
        attrs["schema_version"] = np.int64(self.schema_version)
        attrs["toolkit_version"] = self.toolkit_version
        attrs["split"] = split
        attrs["fps"] = np.int64(self.fps)
        attrs["joint_names"] = list(self.joint_names)
        attrs["icosahedron_template"] = np.asarray(self.icosahedron_template, np.float64)
        attrs["icosahedron_radius"] = np.float64(self.icosahedron_radius)
        attrs["shell_vertex_ids"] = np.asarray(self.shell_vertex_ids, np.int64)
        attrs["body_model_name"] = self.body_model_name
        attrs["body_model_sha256"] = self.body_model_sha256
        attrs["extractors"] = _dumps(self.extractors, indent=None)

    @classmethod
    def read(cls, attrs: h5py.AttributeManager, path: Path | str) -> "ShardAttrs":
        missing = [name for name in ROOT_ATTRS if name not in attrs]
        if missing:
            raise ShardError(path, f"missing root attributes {missing}")
        try:
            extractors = json.loads(attrs["extractors"])
        except json.JSONDecodeError as error:
            raise ShardError(path, f"root attribute 'extractors' is not JSON: {error}") from None
        return cls(
            toolkit_version=str(attrs["toolkit_version"]),
            joint_names=tuple(str(n) for n in attrs["joint_names"]),
            icosahedron_template=np.asarray(attrs["icosahedron_template"], np.float64),
            icosahedron_radius=float(attrs["icosahedron_radius"]),
            shell_vertex_ids=np.asarray(attrs["shell_vertex_ids"], np.int64),
            body_model_name=str(attrs["body_model_name"]),
            body_model_sha256=str(attrs["body_model_sha256"]),
            extractors=extractors,
            fps=int(attrs["fps"]),
            schema_version=int(attrs["schema_version"]),
        )


# --------------------------------------------------------------------------- manifest

@dataclass(frozen=True)
class SourceFile:
    """A raw input file a sequence was made from: path as prep records it, size, content hash."""

    path: str
    bytes: int
    sha256: str


@dataclass(frozen=True)
class SequenceEntry:
    session: str
    split: str
    file: str  # shard file name, relative to the shards folder
    persons: tuple[str, ...]
    frames: int
    seconds: float
    sources: tuple[SourceFile, ...] = ()


@dataclass(frozen=True)
class ShardInfo:
    file: str
    split: str
    sequences: tuple[str, ...]  # in file order
    bytes: int
    sha256: str


@dataclass
class Manifest:
    """`shards/manifest.json`: what was prepared, from what, with which settings, and where."""

    toolkit_version: str
    config: dict  # the full prep configuration, JSON-able
    splits: dict[str, list[str]]  # split -> session ids
    shards: list[ShardInfo]
    sequences: dict[str, SequenceEntry]
    schema_version: int = SHARD_SCHEMA_VERSION

    def to_dict(self) -> dict:
        return {
            "schema_version": self.schema_version,
            "toolkit_version": self.toolkit_version,
            "config": self.config,
            "splits": {split: sorted(sessions) for split, sessions in self.splits.items()},
            "shards": [asdict(info) for info in sorted(self.shards, key=lambda s: s.file)],
            "sequences": {name: asdict(entry) for name, entry in self.sequences.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping, path: Path | str = MANIFEST_NAME) -> "Manifest":
        try:
            return cls(
                schema_version=int(data["schema_version"]),
                toolkit_version=str(data["toolkit_version"]),
                config=dict(data["config"]),
                splits={str(k): _string_list(v, f"splits.{k}") for k, v in data["splits"].items()},
                shards=[_shard_info(s) for s in data["shards"]],
                sequences={str(name): _sequence_entry(name, e) for name, e in data["sequences"].items()},
            )
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise ShardError(path, f"malformed manifest ({type(error).__name__}: {error})") from None


def _shard_info(s: Mapping) -> ShardInfo:
    return ShardInfo(file=str(s["file"]), split=str(s["split"]),
                     sequences=tuple(_string_list(s["sequences"], f"shards.{s['file']}.sequences")),
                     bytes=int(s["bytes"]), sha256=str(s["sha256"]))


def _sequence_entry(name: str, e: Mapping) -> SequenceEntry:
    return SequenceEntry(
        session=str(e["session"]), split=str(e["split"]), file=str(e["file"]),
        persons=tuple(_string_list(e["persons"], f"sequences.{name}.persons")),
        frames=int(e["frames"]), seconds=float(e["seconds"]),
        sources=tuple(SourceFile(str(f["path"]), int(f["bytes"]), str(f["sha256"]))
                      for f in e.get("sources", ())))


def _string_list(value, where: str) -> list[str]:
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{where} must be a list of strings")
    return list(value)


def write_manifest(path: Path | str, manifest: Manifest | Mapping) -> None:
    """Write the manifest atomically as sorted-key, 2-space-indented JSON with a final newline."""
    data = manifest.to_dict() if isinstance(manifest, Manifest) else manifest
    atomic_write_bytes(path, (_dumps(data, indent=2) + "\n").encode("utf-8"))


def read_manifest(path: Path | str) -> Manifest:
    path = Path(path)
    if not path.is_file():
        raise ShardError(path, "no manifest (run sarah-prep to create the shards folder)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ShardError(path, f"unreadable manifest: {error}") from None
    if not isinstance(data, dict):
        raise ShardError(path, "manifest is not a JSON object")
    return Manifest.from_dict(data, path)


def _dumps(data, indent: int | None) -> str:
    return json.dumps(data, sort_keys=True, indent=indent, ensure_ascii=False, allow_nan=False,
                      separators=(",", ": ") if indent else (",", ":"))


# --------------------------------------------------------------------------- atomic, reproducible files

def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write `data` to a temporary name next to `path`, fsync, and rename it into place."""
    path = Path(path)
    tmp = _temporary_name(path)
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _temporary_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def create_h5(path: Path | str, in_memory: bool = False) -> h5py.File:
    """A new HDF5 file (truncating) whose bytes depend only on what is written into it.

    `in_memory`: a scratch file that never touches the disk (`path` only has to be unique among
    this process's open files).
    """
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    # Pinned format range: every object in the oldest encoding that can hold it, never one newer
    # than HDF5 1.10's, so a library upgrade cannot change the bytes written.
    fapl.set_libver_bounds(h5py.h5f.LIBVER_EARLIEST, h5py.h5f.LIBVER_V110)
    if in_memory:
        fapl.set_fapl_core(block_size=1 << 20, backing_store=False)
    fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
    fcpl.set_obj_track_times(False)
    fid = h5py.h5f.create(os.fsencode(path), h5py.h5f.ACC_TRUNC, fcpl=fcpl, fapl=fapl)
    return h5py.File(fid)


def create_group(parent: h5py.Group, name: str) -> h5py.Group:
    gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
    gcpl.set_obj_track_times(False)
    return h5py.Group(h5py.h5g.create(parent.id, name.encode("utf-8"), gcpl=gcpl))


def create_dataset(group: h5py.Group, name: str, data: np.ndarray) -> h5py.Dataset:
    """A time-chunked, gzip+shuffle compressed, fletcher32-checksummed dataset (axis 0 = time).

    The chunks are encoded by `chunks.write_chunks` (same filters, cheaper choices inside deflate).
    """
    data = np.ascontiguousarray(data, dtype=np.asarray(data).dtype.newbyteorder("="))
    chunks = (max(1, min(CHUNK_FRAMES, data.shape[0])),) + data.shape[1:]
    dataset = group.create_dataset(name, shape=data.shape, dtype=data.dtype, chunks=chunks,
                                   compression="gzip", compression_opts=COMPRESSION_LEVEL,
                                   shuffle=True, fletcher32=True, track_times=False)
    write_chunks(dataset, data)
    return dataset


@contextlib.contextmanager
def atomic_h5(path: Path | str) -> Iterator[h5py.File]:
    """Write an HDF5 file under a temporary name; rename it into place only if the block succeeds."""
    path = Path(path)
    tmp = _temporary_name(path)
    handle = create_h5(tmp)
    try:
        yield handle
        handle.close()
        _fsync(tmp)
        os.replace(tmp, path)
    finally:
        handle.close()
        tmp.unlink(missing_ok=True)


def _fsync(path: Path) -> None:
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


def file_sha256(path: Path | str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# --------------------------------------------------------------------------- writing

def _person_arrays(person: ProcessedPerson, attrs: ShardAttrs, frames: int, where: str
                   ) -> dict[str, np.ndarray]:
    """The person's arrays in stored dtypes, checked against the schema; raises ShardError."""
    sizes = {"J": len(attrs.joint_names), "V": len(np.asarray(attrs.shell_vertex_ids))}
    arrays: dict[str, np.ndarray] = {}
    for name, (dtype, tail) in PERSON_DATASETS.items():
        value = np.asarray(getattr(person, name))
        expected = (frames,) + tuple(sizes.get(d, d) for d in tail)
        if value.shape != expected:
            raise ShardError(where, f"{person.name}/{name} has shape {value.shape}, expected {expected}")
        arrays[name] = _cast(value, dtype, f"{where}: {person.name}/{name}")
    for extractor, features in sorted(person.audio.items()):
        value = np.asarray(features)
        if extractor not in attrs.extractors:
            raise ShardError(where, f"{person.name}/audio/{extractor}: extractor not in the shard "
                                    f"attributes {sorted(attrs.extractors)}")
        if value.ndim != 2 or value.shape[0] != frames:
            raise ShardError(where, f"{person.name}/audio/{extractor} has shape {value.shape}, "
                                    f"expected ({frames}, D)")
        arrays[f"audio/{extractor}"] = _cast(value, np.float32,
                                             f"{where}: {person.name}/audio/{extractor}")
    return arrays


def _cast(value: np.ndarray, dtype, where: str) -> np.ndarray:
    if dtype is np.uint8:
        if value.dtype.kind not in "biu" or not np.isin(value, (0, 1)).all():
            raise ShardError(where, f"must be boolean 0/1, got dtype {value.dtype}")
        return value.astype(np.uint8, copy=False)
    if value.dtype.kind != "f":
        raise ShardError(where, f"must be floating point, got dtype {value.dtype}")
    if not np.isfinite(value).all():
        raise ShardError(where, "contains NaN or infinite values")
    return value.astype(np.float32, copy=False)


def _sequence_arrays(seq: ProcessedSequence, attrs: ShardAttrs, split: str
                     ) -> list[tuple[str, dict[str, np.ndarray]]]:
    where = f"sequence {seq.name}"
    if not seq.name or "/" in seq.name or seq.name.startswith("."):
        raise ShardError(where, "a sequence name must be non-empty, without '/', not start with '.'")
    if seq.split != split:
        raise ShardError(where, f"belongs to split {seq.split!r}, this writer writes {split!r}")
    if seq.fps != attrs.fps:
        raise ShardError(where, f"fps {seq.fps} differs from the shard fps {attrs.fps}")
    if len(seq.persons) != 2:
        raise ShardError(where, f"a dyad has 2 persons, got {len(seq.persons)}")
    names = [p.name for p in seq.persons]
    if len(set(names)) != 2 or any(not n or "/" in n or n == "audio" for n in names):
        raise ShardError(where, f"person names must be two distinct valid names, got {names}")
    frames = seq.frames
    if frames < 1:
        raise ShardError(where, "has no frames")
    per_person = [(p.name, _person_arrays(p, attrs, frames, where)) for p in seq.persons]
    extractor_sets = [sorted(k for k in arrays if k.startswith("audio/")) for _, arrays in per_person]
    if extractor_sets[0] != extractor_sets[1]:
        raise ShardError(where, f"persons have different audio features: {extractor_sets}")
    return per_person


def _write_sequence(handle: h5py.File, seq: ProcessedSequence,
                    persons: list[tuple[str, dict[str, np.ndarray]]]) -> None:
    """Build the sequence in a scratch file and copy it in: a group copied (H5Ocopy) is laid out
    differently from one built in place, and prep copies sequences from work files, so every
    writer copies and the same sequence gives the same bytes whichever way it arrives."""
    with create_h5(f"scratch-{os.getpid()}-{id(seq)}", in_memory=True) as scratch:
        _build_sequence(scratch, seq, persons)
        scratch.copy(scratch[seq.name], handle, name=seq.name)


def _build_sequence(handle: h5py.File, seq: ProcessedSequence,
                    persons: list[tuple[str, dict[str, np.ndarray]]]) -> None:
    group = create_group(handle, seq.name)
    group.attrs["session"] = seq.session
    group.attrs["split"] = seq.split
    group.attrs["frames"] = np.int64(seq.frames)
    group.attrs["fps"] = np.int64(seq.fps)
    group.attrs["persons"] = [name for name, _ in persons]
    for name, arrays in persons:
        person_group = create_group(group, name)
        if any(key.startswith("audio/") for key in arrays):
            create_group(person_group, "audio")
        for key, array in arrays.items():
            create_dataset(person_group, key, array)


def write_sequence(handle: h5py.File, seq: ProcessedSequence, attrs: ShardAttrs
                   ) -> list[tuple[str, dict[str, np.ndarray]]]:
    """Check one sequence against the schema (ShardError, nothing written) and write it into an
    open shard-format file whose root attributes are `attrs`; returns each person's arrays as
    stored (`{dataset or "audio/<extractor>": array}`)."""
    persons = _sequence_arrays(seq, attrs, seq.split)
    _write_sequence(handle, seq, persons)
    return persons


def write_shard(path: Path | str, sequences: list[ProcessedSequence], attrs: ShardAttrs | Mapping
                ) -> None:
    """Write `sequences` (all of one split) into one shard-format file at `path`, atomically.

    No size budget and no manifest entry: for a single file such as a per-sequence cache that
    `read_shard` reads back; a shards folder is written with `ShardWriter`.
    """
    path = Path(path)
    splits = {seq.split for seq in sequences}
    if len(splits) != 1:
        raise ShardError(path, f"a shard holds sequences of one split, got {sorted(splits)}")
    names = [seq.name for seq in sequences]
    if len(set(names)) != len(names):
        raise ShardError(path, f"duplicate sequence names in {names}")
    split = splits.pop()
    attrs = ShardAttrs.coerce(attrs)
    checked = [(seq, _sequence_arrays(seq, attrs, split)) for seq in sequences]
    with atomic_h5(path) as handle:
        attrs.write(handle.attrs, split)
        for seq, persons in checked:
            _write_sequence(handle, seq, persons)


def read_shard(path: Path | str) -> tuple[ShardAttrs, list[ProcessedSequence]]:
    """A whole shard-format file back in memory: root attributes and sequences (name order)."""
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        raise ShardError(path, f"cannot open shard: {error}") from None
    with handle:
        return ShardAttrs.read(handle.attrs, path), [_read_sequence(handle[name]) for name in handle]


def _read_sequence(group: h5py.Group) -> ProcessedSequence:
    persons = []
    for name in (str(n) for n in group.attrs["persons"]):
        g = group[name]
        arrays = {key: g[key][()] for key in PERSON_DATASETS}
        arrays["speaking"] = arrays["speaking"].astype(bool)
        arrays["valid"] = arrays["valid"].astype(bool)
        audio = {key: g["audio"][key][()] for key in g["audio"]} if "audio" in g else {}
        persons.append(ProcessedPerson(name=name, audio=audio, **arrays))
    return ProcessedSequence(name=group.name.lstrip("/"), session=str(group.attrs["session"]),
                             split=str(group.attrs["split"]), persons=tuple(persons),
                             fps=int(group.attrs["fps"]))


class ShardWriter:
    """Writes one split's sequences into `<split>-NNNNN.h5` files of at most `max_bytes` each.

    A sequence is never split across files. A new file is started when the current file's size
    plus the next sequence's uncompressed array bytes plus SEQUENCE_OVERHEAD_BYTES would exceed
    `max_bytes` (so only a file holding one sequence larger than the budget can exceed it).
    Files are written under a temporary dot-name and renamed into place when complete; `close`
    then removes this split's files left over from an earlier, larger run. Used as a context
    manager, an exception discards the unfinished file (files already completed stay).

    `add` raises ShardError for a sequence that does not fit the schema before writing anything,
    so the caller may skip it and go on; any other failure during a write aborts the writer.
    """

    def __init__(self, out_dir: Path | str, split: str, attrs: ShardAttrs | Mapping,
                 max_bytes: int = DEFAULT_MAX_BYTES):
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, got {max_bytes}")
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.split = split
        self.attrs = ShardAttrs.coerce(attrs)
        self.max_bytes = int(max_bytes)
        self.entries: dict[str, SequenceEntry] = {}  # sequence -> entry (without sources)
        self._infos: list[ShardInfo] = []
        self._file: h5py.File | None = None
        self._file_sequences: list[str] = []
        self._file_bytes = 0
        self._state = "open"

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def _current_name(self) -> str:
        return shard_name(self.split, len(self._infos))

    def add(self, seq: ProcessedSequence) -> str:
        """Append a sequence; returns the name of the shard file it goes to."""
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        if seq.name in self.entries:
            raise ShardError(f"sequence {seq.name}", "added twice")
        persons = _sequence_arrays(seq, self.attrs, self.split)
        size = sum(a.nbytes for _, arrays in persons for a in arrays.values())
        self._append(seq.name, size, lambda handle: _write_sequence(handle, seq, persons))
        return self._entry(seq.name, seq.session, tuple(name for name, _ in persons),
                           seq.frames, seq.fps)

    def add_copy(self, source: h5py.Group) -> str:
        """Append a sequence group of another file in this format with these root attributes
        (prep's per-sequence work files, written by `write_shard`): its chunks are copied as
        stored, nothing is decoded. The same bytes as `add` of that sequence."""
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        name = source.name.lstrip("/")
        where = f"{source.file.filename}: sequence {name}"
        if name in self.entries:
            raise ShardError(f"sequence {name}", "added twice")
        if ShardAttrs.read(source.file.attrs, source.file.filename).to_json() != self.attrs.to_json():
            raise ShardError(where, "root attributes differ from this writer's")
        if str(source.attrs["split"]) != self.split:
            raise ShardError(where, f"belongs to split {source.attrs['split']!r}, this writer "
                                    f"writes {self.split!r}")
        sizes: list[int] = []
        source.visititems(lambda _, obj: sizes.append(obj.size * obj.dtype.itemsize)
                          if isinstance(obj, h5py.Dataset) else None)
        self._append(name, sum(sizes), lambda handle: source.file.copy(source, handle, name=name))
        return self._entry(name, str(source.attrs["session"]),
                           tuple(str(p) for p in source.attrs["persons"]),
                           int(source.attrs["frames"]), int(source.attrs["fps"]))

    def _append(self, name: str, array_bytes: int, write) -> None:
        size = array_bytes + SEQUENCE_OVERHEAD_BYTES
        try:
            if self._file is not None and self._file_bytes + size > self.max_bytes:
                self._finish_file()
            if self._file is None:
                self._file = create_h5(_temporary_name(self.out_dir / self._current_name))
                self.attrs.write(self._file.attrs, self.split)
            write(self._file)
            self._file.flush()
            self._file_bytes = os.path.getsize(self._file.filename)
        except BaseException:
            self.abort()
            raise
        self._file_sequences.append(name)

    def _entry(self, name: str, session: str, persons: tuple[str, ...], frames: int, fps: int) -> str:
        self.entries[name] = SequenceEntry(session=session, split=self.split, file=self._current_name,
                                           persons=persons, frames=frames, seconds=frames / fps)
        return self._current_name

    def _finish_file(self) -> None:
        final = self.out_dir / self._current_name
        tmp = Path(self._file.filename)
        self._file.close()
        self._file = None
        _fsync(tmp)
        sha256, size = file_sha256(tmp), os.path.getsize(tmp)
        os.replace(tmp, final)
        self._infos.append(ShardInfo(final.name, self.split, tuple(self._file_sequences), size, sha256))
        self._file_sequences = []
        self._file_bytes = 0

    def close(self) -> list[ShardInfo]:
        """Finish the last file, remove stale files of this split, return the files written."""
        if self._state == "closed":
            return list(self._infos)
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        if self._file is not None:
            self._finish_file()
        written = {info.file for info in self._infos}
        for path in self.out_dir.iterdir():
            match = SHARD_FILE_RE.match(path.name)
            if match and match["split"] == self.split and path.name not in written:
                path.unlink()
        self._state = "closed"
        return list(self._infos)

    def abort(self) -> None:
        """Discard the unfinished file; the writer cannot be used afterwards."""
        if self._file is not None:
            tmp = Path(self._file.filename)
            with contextlib.suppress(Exception):
                self._file.close()
            self._file = None
            tmp.unlink(missing_ok=True)
        if self._state == "open":
            self._state = "aborted"


# --------------------------------------------------------------------------- reading

class ShardSet:
    """Read access to a shards folder through its manifest.

    Picklable: it holds paths, never open files. HDF5 files are opened on first use in each
    process (a handle inherited through fork is left alone, not reused), so a DataLoader worker
    opens its own.
    """

    def __init__(self, shards_dir: Path | str):
        self.root = Path(shards_dir)
        self.manifest = read_manifest(self.root / MANIFEST_NAME)
        if self.manifest.schema_version != SHARD_SCHEMA_VERSION:
            raise ShardError(self.root / MANIFEST_NAME,
                             f"schema version {self.manifest.schema_version}, this toolkit reads "
                             f"{SHARD_SCHEMA_VERSION}: prepare the shards again")
        self._attrs: ShardAttrs | None = None
        self._handles: dict[str, h5py.File] = {}
        self._pid = os.getpid()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_handles"] = {}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._pid = os.getpid()

    def sequences(self, split: str | None = None) -> list[str]:
        """Sequence names (sorted), of one split or all."""
        return sorted(name for name, entry in self.manifest.sequences.items()
                      if split is None or entry.split == split)

    def entry(self, sequence: str) -> SequenceEntry:
        try:
            return self.manifest.sequences[sequence]
        except KeyError:
            raise ShardError(self.root / MANIFEST_NAME, f"no sequence {sequence!r}") from None

    @property
    def attrs(self) -> ShardAttrs:
        """Root attributes, as stored in the first shard file (verify checks they all agree)."""
        if self._attrs is None:
            if not self.manifest.shards:
                raise ShardError(self.root / MANIFEST_NAME, "lists no shard files")
            first = sorted(info.file for info in self.manifest.shards)[0]
            self._attrs = ShardAttrs.read(self._open(first).attrs, self.root / first)
        return self._attrs

    def _open(self, file: str) -> h5py.File:
        if os.getpid() != self._pid:
            # Forked from a process that had files open: HDF5 handles must not be shared
            # between processes, so the inherited ones are abandoned and this one opens its own.
            self._handles = {}
            self._pid = os.getpid()
        handle = self._handles.get(file)
        if handle is None:
            path = self.root / file
            try:
                handle = h5py.File(path, "r")
            except OSError as error:
                raise ShardError(path, f"cannot open shard: {error}") from None
            self._handles[file] = handle
        return handle

    def group(self, sequence: str) -> h5py.Group:
        """The sequence's HDF5 group (`/<sequence>`), from its file opened in this process."""
        entry = self.entry(sequence)
        handle = self._open(entry.file)
        if sequence not in handle:
            raise ShardError(self.root / entry.file, f"has no sequence {sequence!r}")
        return handle[sequence]

    def read_sequence(self, sequence: str) -> ProcessedSequence:
        """The whole sequence, back in memory as written."""
        return _read_sequence(self.group(sequence))

    def close(self) -> None:
        if os.getpid() == self._pid:
            for handle in self._handles.values():
                handle.close()
        self._handles = {}


def open_shards(shards_dir: Path | str) -> ShardSet:
    return ShardSet(shards_dir)
