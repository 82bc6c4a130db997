"""The shard format (docs/shard-format.md): schema, manifest, HDF5 I/O, writer and reader.

Everything a caller needs is importable from here; each concept lives in its own module."""

from .h5io import atomic_h5, create_dataset, create_group, create_h5, file_sha256
from .manifest import (Manifest, SequenceEntry, ShardInfo, SourceFile, read_manifest,
                       write_manifest)
from .reader import ShardSet, open_shards, read_shard
from .schema import (CHUNK_FRAMES, DEFAULT_MAX_BYTES, GENDERS, MANIFEST_NAME, PERSON_BODY_DATASETS,
                     PERSON_DATASETS, ROOT_ATTRS,
                     SEQUENCE_ATTRS, SEQUENCE_OVERHEAD_BYTES, SHARD_FILE_RE, STATS_NAME,
                     ProcessedPerson, ProcessedSequence, ShardAttrs, ShardError, canonical_json,
                     sequence_arrays, shard_name)
from .writer import ShardWriter, write_sequence, write_shard

__all__ = ["CHUNK_FRAMES", "DEFAULT_MAX_BYTES", "GENDERS", "MANIFEST_NAME", "PERSON_BODY_DATASETS",
           "PERSON_DATASETS", "ROOT_ATTRS",
           "SEQUENCE_ATTRS", "SEQUENCE_OVERHEAD_BYTES", "SHARD_FILE_RE", "STATS_NAME", "Manifest",
           "ProcessedPerson", "ProcessedSequence", "SequenceEntry", "ShardAttrs", "ShardError",
           "ShardInfo", "ShardSet", "ShardWriter", "SourceFile", "atomic_h5", "canonical_json",
           "create_dataset", "create_group", "create_h5", "file_sha256", "open_shards",
           "read_manifest", "read_shard", "sequence_arrays", "shard_name", "write_manifest",
           "write_sequence", "write_shard"]
