"""The shard schema: names, per-person datasets, root attributes, in-memory records, checks.

A shards folder holds `<split>-NNNNN.h5` files (each at most `max_bytes`, a sequence never split
across files), `manifest.json` (the index, `manifest.py`) and `stats.h5` (sarah_data/stats.py).
The layout is documented in docs/shard-format.md. This package is its only writer (`writer.py`,
through `h5io.py`) and the reference reader (`reader.py`).

Reproducibility: the same sequences with the same attributes, added in the same order, give
byte-identical files. HDF5 stores object timestamps by default; every group and dataset here is
created with time tracking off and the file format pinned (`libver` bounds), so nothing in a file
depends on when or where it was written.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import h5py
import numpy as np

from sarah_data.constants import FPS, SHARD_SCHEMA_VERSION
from sarah_data.loading import DataProblem

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
# Per-person datasets without a time axis (schema 2): the body shape, so motion exports with the
# right body. "B" is the body model's shape-coefficient count.
PERSON_BODY_DATASETS = {
    "betas": (np.float32, ("B",)),
    "rest_joints": (np.float32, ("J", 3)),  # joints at zero pose and zero translation, these betas
}
GENDERS = ("neutral", "female", "male")
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
    # The body shape (schema 2; None in schema 1 shards): betas (B,), rest joints (J, 3) of the
    # body model with these betas at zero pose, and the body model's gender.
    betas: np.ndarray | None = None
    rest_joints: np.ndarray | None = None
    gender: str = "neutral"

    @property
    def frames(self) -> int:
        return int(np.shape(self.valid)[0])

    @property
    def has_body_shape(self) -> bool:
        return self.betas is not None and self.rest_joints is not None


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
            if person.has_body_shape:
                for key in PERSON_BODY_DATASETS:
                    arrays[f"{person.name}/{key}"] = np.asarray(getattr(person, key))
            for extractor, features in person.audio.items():
                arrays[f"{person.name}/audio/{extractor}"] = np.asarray(features)
        return arrays

    @classmethod
    def from_arrays(cls, name: str, session: str, split: str, persons: list[str],
                    arrays: Mapping[str, np.ndarray], fps: int = FPS,
                    genders: Mapping[str, str] | None = None) -> "ProcessedSequence":
        """The inverse of `to_arrays`, given the two person names in order (and their genders,
        "neutral" when not given)."""
        where = f"sequence {name}"
        expected = {f"{p}/{key}" for p in persons for key in PERSON_DATASETS}
        missing = sorted(expected - set(arrays))
        body = {f"{p}/{key}" for p in persons for key in PERSON_BODY_DATASETS} & set(arrays)
        audio_keys = {k for k in arrays if any(k.startswith(f"{p}/audio/") for p in persons)}
        unknown = sorted(set(arrays) - expected - body - audio_keys)
        if missing or unknown:
            raise ShardError(where, f"arrays missing {missing}, unexpected {unknown}")
        people = []
        for person in persons:
            values = {key: arrays[f"{person}/{key}"] for key in PERSON_DATASETS}
            values["speaking"] = np.asarray(values["speaking"]).astype(bool)
            values["valid"] = np.asarray(values["valid"]).astype(bool)
            prefix = f"{person}/audio/"
            audio = {k[len(prefix):]: arrays[k] for k in sorted(audio_keys) if k.startswith(prefix)}
            shape = {key: arrays.get(f"{person}/{key}") for key in PERSON_BODY_DATASETS}
            gender = (genders or {}).get(person, "neutral")
            people.append(ProcessedPerson(name=person, audio=audio, gender=gender, **shape, **values))
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
        attrs["extractors"] = canonical_json(self.extractors, indent=None)

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


def canonical_json(data, indent: int | None) -> str:
    """Sorted keys, no NaN, UTF-8 as is: the same data always gives the same text."""
    return json.dumps(data, sort_keys=True, indent=indent, ensure_ascii=False, allow_nan=False,
                      separators=(",", ": ") if indent else (",", ":"))


# --------------------------------------------------------------------------- checks

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
    if (person.betas is None) != (person.rest_joints is None):
        raise ShardError(where, f"{person.name}: betas and rest_joints go together (both or neither)")
    if person.has_body_shape:
        if person.gender not in GENDERS:
            raise ShardError(where, f"{person.name}: gender {person.gender!r} is not one of {GENDERS}")
        betas = np.asarray(person.betas)
        if betas.ndim != 1 or not betas.size:
            raise ShardError(where, f"{person.name}/betas has shape {betas.shape}, expected (B,)")
        rest = np.asarray(person.rest_joints)
        if rest.shape != (sizes["J"], 3):
            raise ShardError(where, f"{person.name}/rest_joints has shape {rest.shape}, "
                                    f"expected ({sizes['J']}, 3)")
        arrays["betas"] = _cast(betas, np.float32, f"{where}: {person.name}/betas")
        arrays["rest_joints"] = _cast(rest, np.float32, f"{where}: {person.name}/rest_joints")
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


def sequence_arrays(seq: ProcessedSequence, attrs: ShardAttrs, split: str
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

