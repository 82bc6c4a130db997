"""`shards/manifest.json`: what was prepared, from what, with which settings, and where."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

from sarah_data.atomic import atomic_write_text
from sarah_data.constants import SHARD_SCHEMA_VERSION

from .schema import MANIFEST_NAME, ShardError, canonical_json

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
    atomic_write_text(path, canonical_json(data, indent=2) + "\n", durable=True)


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

