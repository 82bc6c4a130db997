import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from sarah_data import chunks, shards
from sarah_data.constants import JOINT_NAMES, SHARD_SCHEMA_VERSION
from sarah_data.icosahedron import DEFAULT_RADIUS, TEMPLATE
from sarah_data.shards import (CHUNK_FRAMES, Manifest, ProcessedPerson, ProcessedSequence, ShardAttrs,
                               ShardError, ShardWriter, SourceFile, open_shards, read_manifest, read_shard,
                               write_manifest, write_shard)
from sarah_data.verify import format_summary, summarize, verify_shards

J, V = 3, 5
EXTRACTORS = {"logmel": 4, "hubert-large": 6}


def make_attrs() -> ShardAttrs:
    return ShardAttrs(toolkit_version="0.1.0", joint_names=JOINT_NAMES[:J],
                      icosahedron_template=TEMPLATE, icosahedron_radius=DEFAULT_RADIUS,
                      shell_vertex_ids=np.arange(V) * 7, body_model_name="procedural",
                      body_model_sha256="ab" * 32,
                      extractors={name: {"dim": dim} for name, dim in EXTRACTORS.items()})


def make_person(rng, name: str, frames: int, extractors=EXTRACTORS) -> ProcessedPerson:
    f32 = lambda *shape: rng.normal(size=(frames,) + shape).astype(np.float32)  # noqa: E731
    return ProcessedPerson(
        name=name, icosahedra=f32(J, 12, 3), shell=f32(V, 3), head=f32(2), gaze=f32(),
        speaking=rng.random(frames) < 0.3, valid=rng.random(frames) < 0.9,
        root_position=f32(3), root_rotation=f32(3, 3),
        audio={e: f32(d) for e, d in extractors.items()})


def make_sequence(rng, name: str, split: str = "train", frames: int = 50, session: str | None = None,
                  extractors=EXTRACTORS) -> ProcessedSequence:
    return ProcessedSequence(name=name, session=session or f"c--{name}", split=split,
                             persons=(make_person(rng, "AAA111", frames, extractors),
                                      make_person(rng, "BBB222", frames, extractors)))


def write_folder(root: Path, sequences: list[ProcessedSequence], max_bytes=shards.DEFAULT_MAX_BYTES,
                 attrs: ShardAttrs | None = None) -> Manifest:
    """Shards plus a manifest, the way prep assembles them."""
    infos, entries = [], {}
    for split in ("train", "val", "test"):
        with ShardWriter(root, split, attrs or make_attrs(), max_bytes=max_bytes) as writer:
            for seq in sequences:
                if seq.split == split:
                    writer.add(seq)
        infos += writer.close()
        entries.update(writer.entries)
    entries = {name: dataclasses.replace(e, sources=(SourceFile(f"raw/{name}.npy", 10, "0" * 64),))
               for name, e in entries.items()}
    manifest = Manifest(toolkit_version="0.1.0", config={"window": 400},
                        splits={s: sorted({e.session for e in entries.values() if e.split == s})
                                for s in ("train", "val", "test")},
                        shards=infos, sequences=entries)
    write_manifest(root / shards.MANIFEST_NAME, manifest)
    return manifest


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def assert_sequences_equal(a: ProcessedSequence, b: ProcessedSequence) -> None:
    assert (a.name, a.session, a.split, a.fps) == (b.name, b.session, b.split, b.fps)
    for pa, pb in zip(a.persons, b.persons, strict=True):
        assert pa.name == pb.name
        for key in shards.PERSON_DATASETS:
            x, y = np.asarray(getattr(pa, key)), np.asarray(getattr(pb, key))
            assert x.shape == y.shape and np.array_equal(x, y), key
        assert sorted(pa.audio) == sorted(pb.audio)
        for key in pa.audio:
            assert pb.audio[key].dtype == np.float32
            assert np.array_equal(pa.audio[key], pb.audio[key])


def test_round_trip_plain_h5py_and_api(tmp_path):
    rng = np.random.default_rng(0)
    seqs = [make_sequence(rng, "s1", frames=900), make_sequence(rng, "s2", "val", frames=30)]
    write_folder(tmp_path, seqs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["manifest.json", "train-00000.h5",
                                                           "val-00000.h5"]
    with h5py.File(tmp_path / "train-00000.h5", "r") as f:  # the docs' plain-h5py reading
        assert f.attrs["schema_version"] == SHARD_SCHEMA_VERSION
        assert list(f.attrs["joint_names"]) == list(JOINT_NAMES[:J])
        assert json.loads(f.attrs["extractors"]) == {"hubert-large": {"dim": 6}, "logmel": {"dim": 4}}
        np.testing.assert_array_equal(f.attrs["icosahedron_template"], TEMPLATE)
        seq = f["s1"]
        assert dict(seq.attrs) | {"persons": list(seq.attrs["persons"])} == {
            "session": "c--s1", "split": "train", "frames": 900, "fps": 30, "persons": ["AAA111", "BBB222"]}
        ico = seq["AAA111/icosahedra"]
        assert ico.shape == (900, J, 12, 3) and ico.dtype == np.float32
        assert ico.chunks == (CHUNK_FRAMES, J, 12, 3) and ico.compression == "gzip" and ico.shuffle and ico.fletcher32
        assert seq["BBB222/audio/logmel"].shape == (900, 4)
        assert seq["AAA111/valid"].dtype == np.uint8
        np.testing.assert_array_equal(seq["BBB222/shell"][()], seqs[0].persons[1].shell)
    shard_set = open_shards(tmp_path)
    assert shard_set.sequences() == ["s1", "s2"] and shard_set.sequences("val") == ["s2"]
    for seq in seqs:
        assert_sequences_equal(seq, shard_set.read_sequence(seq.name))
    assert shard_set.attrs.to_json() == make_attrs().to_json()
    shard_set.close()
    assert verify_shards(tmp_path) == []


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.integers(1, 1300), seed=st.integers(0, 1000), with_audio=st.booleans())
def test_round_trip_any_length(tmp_path_factory, frames, seed, with_audio):
    root = tmp_path_factory.mktemp("shards")
    seq = make_sequence(np.random.default_rng(seed), "s", frames=frames,
                        extractors=EXTRACTORS if with_audio else {})
    write_folder(root, [seq])
    assert_sequences_equal(seq, open_shards(root).read_sequence("s"))
    assert verify_shards(root) == []


def test_byte_identical_repeat_writes(tmp_path):
    def build(seed):
        rng = np.random.default_rng(seed)
        return [make_sequence(rng, f"s{i}", frames=120) for i in range(3)]

    write_folder(tmp_path / "a", build(1), max_bytes=60_000 + shards.SEQUENCE_OVERHEAD_BYTES)
    time.sleep(1.1)  # HDF5 timestamps have one-second resolution: make them differ if stored
    write_folder(tmp_path / "b", build(1), max_bytes=60_000 + shards.SEQUENCE_OVERHEAD_BYTES)
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert len(files) >= 3  # several shards and the manifest
    assert files == sorted(p.name for p in (tmp_path / "b").iterdir())
    for name in files:
        assert sha(tmp_path / "a" / name) == sha(tmp_path / "b" / name), name


def test_files_respect_the_byte_budget(tmp_path):
    rng = np.random.default_rng(2)
    seqs = [make_sequence(rng, f"s{i:02d}", frames=int(f)) for i, f in enumerate(rng.integers(50, 300, 12))]
    budget = 600_000
    manifest = write_folder(tmp_path, seqs, max_bytes=budget)
    infos = sorted(manifest.shards, key=lambda s: s.file)
    assert len(infos) > 2
    assert [i.file for i in infos] == [f"train-{k:05d}.h5" for k in range(len(infos))]
    assert [s for i in infos for s in i.sequences] == [s.name for s in seqs]  # order kept, none split
    for info in infos:
        assert (tmp_path / info.file).stat().st_size == info.bytes <= budget
        assert sha(tmp_path / info.file) == info.sha256
    with pytest.raises(ShardError):  # the writer checks its input before writing anything
        ShardWriter(tmp_path / "x", "train", make_attrs()).add(make_sequence(rng, "v", "val"))


def test_oversized_sequence_gets_its_own_file(tmp_path):
    rng = np.random.default_rng(3)
    seqs = [make_sequence(rng, "a", frames=20), make_sequence(rng, "big", frames=600),
            make_sequence(rng, "c", frames=20)]
    manifest = write_folder(tmp_path, seqs, max_bytes=200_000)
    assert [i.sequences for i in manifest.shards] == [("a",), ("big",), ("c",)]
    assert verify_shards(tmp_path) == []


def test_close_removes_stale_files_of_the_split_only(tmp_path):
    rng = np.random.default_rng(4)
    for name in ("train-00000.h5", "train-00007.h5", "val-00000.h5"):
        (tmp_path / name).write_bytes(b"old")
    with ShardWriter(tmp_path, "train", make_attrs()) as writer:
        writer.add(make_sequence(rng, "s"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train-00000.h5", "val-00000.h5"]
    assert (tmp_path / "train-00000.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"


def test_failure_mid_write_leaves_no_file(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    first, second = make_sequence(rng, "s1"), make_sequence(rng, "s2")
    real, calls = shards.writer.create_dataset, []

    def failing(group, name, data):
        calls.append(name)
        if len(calls) == 30:  # well inside the second sequence
            raise OSError("disk full")
        return real(group, name, data)

    monkeypatch.setattr(shards.writer, "create_dataset", failing)
    with pytest.raises(OSError, match="disk full"):
        with ShardWriter(tmp_path, "train", make_attrs()) as writer:
            writer.add(first)
            # still being written: nothing may exist under the final name yet
            assert not (tmp_path / "train-00000.h5").exists()
            writer.add(second)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="aborted"):
        writer.add(first)


def test_invalid_sequence_is_refused_before_writing(tmp_path):
    rng = np.random.default_rng(6)
    good, bad = make_sequence(rng, "good"), make_sequence(rng, "bad")
    bad.persons[1].gaze[3] = np.nan
    wrong_shape = make_sequence(rng, "wrong")
    wrong_shape.persons[0].shell = wrong_shape.persons[0].shell[:, :2]
    with ShardWriter(tmp_path, "train", make_attrs()) as writer:
        writer.add(good)
        with pytest.raises(ShardError, match="BBB222/gaze.*NaN"):
            writer.add(bad)
        with pytest.raises(ShardError, match=r"AAA111/shell has shape \(50, 2, 3\)"):
            writer.add(wrong_shape)
    infos = writer.close()
    assert [i.sequences for i in infos] == [("good",)]


def _corrupt_chunk_byte(path: Path, dataset: str) -> None:
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(0)
    with open(path, "r+b") as handle:
        handle.seek(info.byte_offset + info.size // 2)
        byte = handle.read(1)
        handle.seek(-1, os.SEEK_CUR)
        handle.write(bytes([byte[0] ^ 0xFF]))


def test_verify_catches_corruption_missing_files_and_mismatches(tmp_path):
    rng = np.random.default_rng(7)
    seqs = [make_sequence(rng, "s1"), make_sequence(rng, "s2", "val"), make_sequence(rng, "s3", "test")]
    manifest = write_folder(tmp_path, seqs)
    assert verify_shards(tmp_path) == []

    # a flipped byte inside compressed data: the sha256 check and the HDF5 checksum both see it
    _corrupt_chunk_byte(tmp_path / "train-00000.h5", "s1/AAA111/shell")
    problems = verify_shards(tmp_path)
    assert any("train-00000.h5: sha256 differs" in p for p in problems)
    assert any("s1: AAA111/shell: unreadable" in p for p in problems)
    # even with a manifest updated to the corrupted file, the checksum catches it
    data = json.loads((tmp_path / "manifest.json").read_text())
    data["shards"][1]["sha256"] = sha(tmp_path / "train-00000.h5")
    write_manifest(tmp_path / "manifest.json", data)
    assert [p for p in verify_shards(tmp_path) if "unreadable" in p] and not [
        p for p in verify_shards(tmp_path) if "sha256" in p]

    (tmp_path / "val-00000.h5").unlink()
    assert "val-00000.h5: missing" in verify_shards(tmp_path)

    write_folder(tmp_path, seqs)  # fresh again
    data = json.loads((tmp_path / "manifest.json").read_text())
    data["sequences"]["s3"]["frames"] = 51
    data["shards"][0]["sequences"] = []
    write_manifest(tmp_path / "manifest.json", data)
    problems = verify_shards(tmp_path)
    assert any("test-00000.h5: holds sequences ['s3'], manifest lists []" in p for p in problems)
    assert any("sequence s3 has split/persons/frames" in p for p in problems)

    write_manifest(tmp_path / "manifest.json", manifest)
    (tmp_path / "train-00001.h5").write_bytes(b"stray")
    assert verify_shards(tmp_path) == ["train-00001.h5: shard file not listed in manifest.json"]


def test_manifest_round_trip_and_stable_format(tmp_path):
    rng = np.random.default_rng(8)
    manifest = write_folder(tmp_path, [make_sequence(rng, "s1"), make_sequence(rng, "s2", "val")])
    text = (tmp_path / "manifest.json").read_text()
    data = json.loads(text)
    assert text == json.dumps(data, sort_keys=True, indent=2, ensure_ascii=False) + "\n"
    assert read_manifest(tmp_path / "manifest.json") == Manifest.from_dict(manifest.to_dict())
    assert data["sequences"]["s1"] == {
        "session": "c--s1", "split": "train", "file": "train-00000.h5",
        "persons": ["AAA111", "BBB222"], "frames": 50, "seconds": 50 / 30,
        "sources": [{"path": "raw/s1.npy", "bytes": 10, "sha256": "0" * 64}]}
    assert data["splits"] == {"train": ["c--s1"], "val": ["c--s2"], "test": []}
    with pytest.raises(ShardError, match="malformed manifest"):
        Manifest.from_dict({"schema_version": 1})
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_summarize_counts_hours_and_features(tmp_path):
    rng = np.random.default_rng(9)
    seqs = [make_sequence(rng, "s1", frames=300), make_sequence(rng, "s2", frames=600),
            make_sequence(rng, "s3", "test", frames=90, extractors={"logmel": 4})]
    write_folder(tmp_path, seqs)
    rows = {row["split"]: row for row in summarize(tmp_path)}
    assert list(rows) == ["train", "test", "total"]
    assert rows["train"]["sequences"] == 2 and rows["total"]["sequences"] == 3
    assert rows["train"]["hours"] == pytest.approx(900 / 30 / 3600)
    both = [np.logical_and(s.persons[0].valid, s.persons[1].valid) for s in seqs]
    assert rows["total"]["tracked_hours"] == pytest.approx(sum(b.sum() for b in both) / 30 / 3600)
    assert rows["test"]["logmel hours"] == pytest.approx(90 / 30 / 3600)
    assert rows["test"]["hubert-large hours"] == 0
    table = format_summary(summarize(tmp_path))
    assert table.splitlines()[0].split()[:3] == ["split", "files", "bytes"] and "total" in table


def test_docs_snippet_reads_a_shard(tmp_path, monkeypatch, capsys):
    doc = (Path(__file__).parents[1] / "docs" / "shard-format.md").read_text()
    snippet = doc.split("```python\n", 1)[1].split("```", 1)[0]
    assert len(snippet.strip().splitlines()) <= 11
    rng = np.random.default_rng(10)
    write_folder(tmp_path / "shards", [make_sequence(rng, "s1", frames=500),
                                       make_sequence(rng, "s2", frames=20, extractors={})])
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, "shard-format.md", "exec"), {})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{SHARD_SCHEMA_VERSION} {list(JOINT_NAMES[:3])}"
    assert lines[1].startswith(f"s1 500 (400, {J}, 12, 3) (400, 2) ")
    assert lines[1].endswith(" ['hubert-large', 'logmel']")
    assert lines[2].startswith(f"s2 20 (20, {J}, 12, 3) (20, 2) ") and lines[2].endswith(" []")


def test_single_file_write_shard_matches_the_writer(tmp_path):
    rng = np.random.default_rng(11)
    seqs = [make_sequence(rng, "s1", frames=70), make_sequence(rng, "s2", frames=5, extractors={})]
    write_shard(tmp_path / "cache.h5", seqs, make_attrs())
    with ShardWriter(tmp_path / "folder", "train", make_attrs()) as writer:
        for seq in seqs:
            writer.add(seq)
    assert sha(tmp_path / "cache.h5") == sha(tmp_path / "folder" / "train-00000.h5")
    attrs, back = read_shard(tmp_path / "cache.h5")
    assert attrs.to_json() == make_attrs().to_json()
    for a, b in zip(seqs, back, strict=True):
        assert_sequences_equal(a, b)
    with pytest.raises(ShardError, match="one split"):
        write_shard(tmp_path / "mixed.h5", [seqs[0], make_sequence(rng, "v", "val")], make_attrs())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache.h5", "folder"]


def test_flat_arrays_and_mapping_attrs(tmp_path):
    rng = np.random.default_rng(12)
    seq = make_sequence(rng, "s1", frames=30)
    arrays = seq.to_arrays()
    assert arrays["BBB222/audio/logmel"].shape == (30, 4) and "AAA111/valid" in arrays
    back = ProcessedSequence.from_arrays("s1", "c--s1", "train", ["AAA111", "BBB222"], arrays)
    assert_sequences_equal(seq, back)
    with pytest.raises(ShardError, match=r"missing \['AAA111/gaze'\], unexpected \['AAA111/extra'\]"):
        ProcessedSequence.from_arrays("s1", "c--s1", "train", ["AAA111", "BBB222"],
                                      {**{k: v for k, v in arrays.items() if k != "AAA111/gaze"},
                                       "AAA111/extra": np.zeros(30)})
    mapping = {f: getattr(make_attrs(), f) for f in ShardAttrs.__dataclass_fields__}
    write_shard(tmp_path / "a.h5", [seq], mapping)
    write_shard(tmp_path / "b.h5", [seq], make_attrs())
    assert sha(tmp_path / "a.h5") == sha(tmp_path / "b.h5")
    with pytest.raises(ValueError, match="unit icosahedron"):
        ShardWriter(tmp_path, "train", {**mapping, "icosahedron_template": TEMPLATE * DEFAULT_RADIUS})
    with pytest.raises(ValueError, match="unknown shard root attributes"):
        ShardWriter(tmp_path, "train", {**mapping, "colour": "red"})
    manifest = write_folder(tmp_path / "f", [seq]).to_dict()
    manifest["splits"]["train"] = {"sessions": ["c--s1"]}
    with pytest.raises(ShardError, match="splits.train must be a list"):
        Manifest.from_dict(manifest)


# --------------------------------------------------------------------------- chunk encoding

def _fletcher32_c_loop(data: bytes) -> int:
    """A literal port of HDF5's H5_checksum_fletcher32 (blocks of 360 words, end-around carry)."""
    sum1 = sum2 = 0
    words, i = len(data) // 2, 0
    while words:
        block = min(words, 360)
        words -= block
        for _ in range(block):
            sum1 += (data[i] << 8) | data[i + 1]
            sum2 += sum1
            i += 2
        sum1, sum2 = (sum1 & 0xFFFF) + (sum1 >> 16), (sum2 & 0xFFFF) + (sum2 >> 16)
    if len(data) % 2:
        sum1 += data[i] << 8
        sum2 += sum1
        sum1, sum2 = (sum1 & 0xFFFF) + (sum1 >> 16), (sum2 & 0xFFFF) + (sum2 >> 16)
    sum1, sum2 = (sum1 & 0xFFFF) + (sum1 >> 16), (sum2 & 0xFFFF) + (sum2 >> 16)
    return (sum2 << 16) | sum1


def test_fletcher32_matches_hdf5():
    rng = np.random.default_rng(13)
    cases = [b"", b"\x00", b"\x00" * 1001, b"\xff" * 2000, b"\xff" * 2001, b"\x01", b"\x00\x00\x00\x01"]
    cases += [rng.integers(0, 256, rng.integers(1, 3000)).astype(np.uint8).tobytes() for _ in range(60)]
    cases += [rng.choice([0, 255], rng.integers(1, 3000)).astype(np.uint8).tobytes() for _ in range(30)]
    for data in cases:
        assert chunks.fletcher32(data) == _fletcher32_c_loop(data), data[:16]


@pytest.mark.parametrize("shape,dtype", [((250, 3, 4), np.float32), ((100, 7), np.float32),
                                         ((37,), np.uint8), ((1,), np.float32), ((205, 2), np.float64)])
def test_encoded_chunks_read_back_through_hdf5s_own_filters(tmp_path, shape, dtype):
    """Direct-written chunks decode with HDF5's shuffle, inflate and fletcher32 (edge chunks too),
    and HDF5's own checksum of a pipeline-written chunk is what ours computes."""
    rng = np.random.default_rng(14)
    data = (rng.normal(size=shape) * 3).astype(dtype) if dtype != np.uint8 else rng.integers(0, 2, shape, dtype=dtype)
    with shards.create_h5(tmp_path / "c.h5") as handle:
        ours = shards.create_dataset(handle, "ours", data)
        np.testing.assert_array_equal(ours[()], data)
        assert ours.compression == "gzip" and ours.shuffle and ours.fletcher32
        theirs = handle.create_dataset("theirs", data=data, chunks=ours.chunks, compression="gzip",
                                       shuffle=True, fletcher32=True)
        _, raw = theirs.id.read_direct_chunk((0,) * data.ndim)
        assert chunks.fletcher32(raw[:-4]) == int.from_bytes(raw[-4:], "little")
        # a flipped bit in an encoded chunk fails HDF5's checksum on read
        _, raw = ours.id.read_direct_chunk((0,) * data.ndim)
        ours.id.write_direct_chunk((0,) * data.ndim, raw[:5] + bytes([raw[5] ^ 1]) + raw[6:])
        with pytest.raises(OSError):
            ours[()]


def test_icosahedron_template_keeps_trimesh_vertex_order():
    """Shards store vertices in trimesh's icosahedron order; icosahedron.py writes it out."""
    trimesh = pytest.importorskip("trimesh")
    vertices = np.asarray(trimesh.creation.icosahedron().vertices, dtype=np.float64)
    np.testing.assert_array_equal(TEMPLATE, vertices / np.linalg.norm(vertices, axis=1, keepdims=True))
