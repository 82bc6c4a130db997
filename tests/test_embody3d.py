"""The Embody 3D corpus reader: the real manifest, short sequences on disk, every skip reason."""

from __future__ import annotations

import json
import random
import shutil
import string
import tempfile
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from embody_layout import (REAL_MANIFEST, manifest_entries, persons_of, with_frame_range,
                           write_manifest, write_sequence)
from sarah_data.constants import SAMPLES_PER_FRAME, SMPLX_PARAM_WIDTHS
from sarah_data.embody3d import (AUDIO_FOLDERS, PARAM_KEYS, DataProblem, check_files,
                                 load_person, parse_sequence_name, read_corpus)

pytestmark = pytest.mark.skipif(not REAL_MANIFEST.exists(), reason="reference manifest absent")


def real_manifest() -> dict:
    return json.loads(REAL_MANIFEST.read_text())


def real_sequences() -> dict[str, dict[str, dict]]:
    """The real manifest regrouped as {sequence: {subject: entry}}."""
    out: dict[str, dict[str, dict]] = {}
    for subject, sequences in real_manifest().items():
        for sequence, entry in sequences.items():
            out.setdefault(sequence, {})[subject] = entry
    return out


@pytest.fixture(scope="module")
def real_section(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("raw") / "aiagent"
    folder.mkdir()
    shutil.copy(REAL_MANIFEST, folder / "dataset.json")
    return folder


# ----------------------------------------------------------------------------- real manifest

def test_real_manifest_pairs_and_skips(real_section):
    corpus = read_corpus(real_section)
    assert corpus.problems == []
    # 563 two-person sequences in 36 sessions; the 14 without audio are skipped, not dropped.
    assert len(corpus.pairs) == 549
    assert corpus.skipped_by_kind == {"no-audio": 14}
    assert all(s.path == real_section / "dataset.json" for s in corpus.skipped)
    listed = {p.sequence for p in corpus.pairs} | {s.sequence for s in corpus.skipped}
    assert len(listed) == 563
    assert len({parse_sequence_name(q).session for q in listed}) == 36
    # One session's sequences all lack audio.
    assert len(corpus.sessions) == 35
    assert corpus.counts["pairs"] == 549 and corpus.counts["skipped"] == 14
    assert corpus.counts["frames"] == sum(p.length for p in corpus.pairs)


def test_real_manifest_without_audio_requirement(real_section):
    corpus = read_corpus([real_section], require_audio=False)
    assert corpus.skipped == [] and corpus.problems == []
    assert corpus.counts["pairs"] == 563
    assert corpus.counts["sessions"] == 36
    assert corpus.counts["subjects"] == 70
    hours = corpus.counts["frames"] / 30 / 3600
    assert round(hours, 1) == 25.6  # the README's 25.6 dyad-hours
    assert sum(not p.has_audio for p in corpus.pairs) == 14
    silent = next(p for p in corpus.pairs if not p.has_audio)
    assert all(f.audio is None for f in silent.files.values())


def test_real_manifest_records(real_section):
    corpus = read_corpus(real_section)
    truth = real_sequences()
    names = [p.sequence for p in corpus.pairs]
    assert names == sorted(names)
    for pair in corpus.pairs:
        assert pair.folder == real_section
        assert pair.persons == tuple(sorted(truth[pair.sequence]))
        assert pair.persons == tuple(sorted(persons_of(pair.sequence)))
        assert pair.session == "--".join(pair.sequence.split("--")[:3])
        assert pair.recorded == datetime.strptime(pair.sequence[3:17], "%Y%m%d--%H%M")
        assert pair.length == pair.end - pair.start + 1
        assert pair.length == truth[pair.sequence][pair.persons[0]]["length"]
        assert pair.scene == pair.sequence.split("--")[7]
        for subject, files in pair.files.items():
            base = real_section / pair.sequence / subject
            # Rebased: the manifest's /social_ai/... prefix is gone.
            assert files.audio == base / "audio_separated" / f"{pair.sequence}.wav"
            assert files.missing == base / "missing" / f"{pair.sequence}.npy"
            assert files.params == {f: base / f / f"{pair.sequence}.npy"
                                    for f in SMPLX_PARAM_WIDTHS}


def test_reading_is_deterministic(real_section):
    assert read_corpus(real_section) == read_corpus([str(real_section)])


@settings(max_examples=10, deadline=None)
@given(st.randoms(use_true_random=False))
def test_result_does_not_depend_on_manifest_order(rnd: random.Random):
    sequences = real_sequences()
    chosen = sorted(sequences)[::25]  # 23 sequences, including some without audio
    with tempfile.TemporaryDirectory() as tmp:
        a, b = Path(tmp) / "a" / "aiagent", Path(tmp) / "b" / "aiagent"
        write_manifest(a, {q: sequences[q] for q in chosen})
        shuffled = chosen[:]
        rnd.shuffle(shuffled)
        write_manifest(b, {q: dict(reversed(sequences[q].items())) for q in shuffled})
        ca, cb = read_corpus(a), read_corpus(b)
    assert [p.sequence for p in ca.pairs] == [p.sequence for p in cb.pairs]
    assert [p.persons for p in ca.pairs] == [p.persons for p in cb.pairs]
    assert [(s.sequence, s.reason) for s in ca.skipped] == \
        [(s.sequence, s.reason) for s in cb.skipped]


# ----------------------------------------------------------------------------- names

_ids = st.text(string.ascii_uppercase + string.digits, min_size=6, max_size=6)


@settings(max_examples=60, deadline=None)
@given(when=st.datetimes(datetime(2020, 1, 1), datetime(2030, 12, 31)),
       ids=st.lists(_ids, min_size=2, max_size=2, unique=True),
       prior=st.sampled_from(["MotionPrior", "MotionPrior2", "MotionPrior13"]),
       scene=st.text(string.ascii_letters + string.digits + "_", min_size=1, max_size=30),
       start=st.integers(0, 999_999), length=st.integers(1, 100_000))
def test_sequence_name_round_trip(when, ids, prior, scene, start, length):
    when = when.replace(second=0, microsecond=0)
    end = start + length - 1
    name = (f"c--{when:%Y%m%d--%H%M}--{ids[0]}--{ids[1]}--pilot--{prior}--{scene}"
            f"--{start:06d}-{end:06d}")
    parsed = parse_sequence_name(name)
    assert parsed.session == f"c--{when:%Y%m%d--%H%M}"
    assert parsed.recorded == when
    assert parsed.named_persons == tuple(ids)
    assert (parsed.motion_prior, parsed.scene) == (prior, scene)
    assert (parsed.start, parsed.end, parsed.length) == (start, end, length)


@pytest.mark.parametrize("name, reason", [
    ("c--20250321--1019--WBM368--BVO565--pilot--MotionPrior2--scene--000010", "does not match"),
    ("c--20250321--1019--WBM368--pilot--MotionPrior2--scene--000001-000010", "does not match"),
    ("c--20251340--1019--WBM368--BVO565--pilot--MotionPrior2--scene--000001-000010",
     "invalid capture date"),
    ("c--20250321--1019--WBM368--WBM368--pilot--MotionPrior2--scene--000001-000010",
     "same person twice"),
    ("c--20250321--1019--WBM368--BVO565--pilot--MotionPrior2--scene--000010-000001",
     "ends before it starts"),
])
def test_malformed_sequence_names(name, reason):
    with pytest.raises(ValueError, match=reason):
        parse_sequence_name(name)


# ----------------------------------------------------------------------------- short sequences

def short_real_sequences(lengths=(5, 12, 30)) -> list[str]:
    """Real sequence names (with audio) renamed to short frame ranges."""
    truth = real_sequences()
    with_audio = [q for q in sorted(truth) if all(e["audio"] for e in truth[q].values())]
    return [with_frame_range(q, 1000 + i, n) for i, (q, n) in enumerate(zip(with_audio, lengths))]


@pytest.mark.parametrize("listed", AUDIO_FOLDERS)
@pytest.mark.parametrize("on_disk", AUDIO_FOLDERS)
def test_load_short_sequences(tmp_path, listed, on_disk):
    folder = tmp_path / "aiagent"
    names = short_real_sequences()
    write_manifest(folder, {q: manifest_entries(q, parse_sequence_name(q).length,
                                                audio_folder=listed) for q in names})
    written = {q: write_sequence(folder, q, seed=i, audio_folder=on_disk)
               for i, q in enumerate(names)}
    corpus = read_corpus(folder)
    assert corpus.skipped == [] and corpus.problems == []
    assert [p.sequence for p in corpus.pairs] == sorted(names)
    assert check_files(corpus) == []
    for pair in corpus.pairs:
        for person in pair.persons:
            truth = written[pair.sequence][person]
            assert pair.files[person].audio == \
                folder / pair.sequence / person / on_disk / f"{pair.sequence}.wav"
            arrays = load_person(pair, person)
            assert arrays.warnings == []
            assert arrays.length == pair.length
            assert set(arrays.params) == {"betas", "body_pose", "global_orient", "transl",
                                          "left_hand_pose", "right_hand_pose"}
            for folder_name, key in PARAM_KEYS.items():
                assert arrays.params[key].shape == (pair.length, SMPLX_PARAM_WIDTHS[folder_name])
                np.testing.assert_array_equal(arrays.params[key], truth["params"][folder_name])
            assert arrays.valid.dtype == bool
            np.testing.assert_array_equal(arrays.valid, truth["mask"] == 1)
            assert arrays.audio.dtype == np.float32
            assert arrays.audio.shape == (pair.length * SAMPLES_PER_FRAME,)
            np.testing.assert_array_equal(arrays.audio, truth["audio"])


def test_load_without_audio_and_unknown_person(tmp_path):
    folder = tmp_path / "aiagent"
    name = short_real_sequences()[0]
    write_manifest(folder, {name: manifest_entries(name, 5, audio=False)})
    write_sequence(folder, name, audio=False)
    assert read_corpus(folder).skipped_by_kind == {"no-audio": 1}
    pair, = read_corpus(folder, require_audio=False).pairs
    assert load_person(pair, pair.persons[1]).audio is None
    with pytest.raises(ValueError, match="is not a person of"):
        load_person(pair, "NOBODY")


def _one_written_pair(tmp_path):
    """One real-named sequence of 5 frames written into a section folder: (pair, folder)."""
    folder = tmp_path / "aiagent"
    name = short_real_sequences()[0]
    write_manifest(folder, {name: manifest_entries(name, 5)})
    write_sequence(folder, name)
    pair, = read_corpus(folder).pairs
    return pair, folder


def test_check_files_names_missing_files(tmp_path):
    pair, folder = _one_written_pair(tmp_path)
    person = pair.persons[0]
    pair.files[person].missing.unlink()
    pair.files[person].audio.unlink()
    problems = check_files(read_corpus(folder))
    assert [p.path for p in problems] == [pair.files[person].missing, pair.files[person].audio]
    assert all(p.reason.startswith("missing file") for p in problems)
    assert "also looked in separated_audio/" in problems[1].reason
    with pytest.raises(DataProblem, match="missing file"):
        load_person(pair, person)


# ----------------------------------------------------------------------------- skips, problems

BASE = "c--20250321--1019--AAA111--BBB222--pilot--MotionPrior2--AIAGENT_scene_009--000100-000109"


def variant(n: int) -> str:
    """A distinct well-formed sequence name of 10 frames."""
    return with_frame_range(BASE, 200 + 20 * n, 10)


def test_every_skip_reason(tmp_path):
    good = variant(0)
    cases: dict[str, tuple[dict[str, dict], str, str]] = {}

    def case(kind, reason, name, entries):
        cases[name] = (entries, kind, reason)

    case("no-audio", "no audio", variant(1), manifest_entries(variant(1), 10, audio=False))
    e = manifest_entries(variant(2), 10)
    case("missing-partner", "no entry for partner BBB222", variant(2), {"AAA111": e["AAA111"]})
    bad_name = BASE.replace("--pilot--", "--oops--")
    case("malformed-name", "malformed sequence name", bad_name, manifest_entries(bad_name, 10))
    case("length-mismatch", "name's frame range 260-269 gives 10", variant(3),
         manifest_entries(variant(3), 11))
    e = manifest_entries(variant(4), 10)
    e["BBB222"]["length"] = 9
    case("length-mismatch", "persons disagree on length", variant(4), e)
    e = manifest_entries(variant(5), 10)
    e["BBB222"]["audio"] = None
    case("audio-mismatch", "audio listed for AAA111 but not for BBB222", variant(5), e)
    e = manifest_entries(variant(6), 10)
    e["AAA111"]["multiperson"] = ["BBB222", "CCC333"]
    case("not-two-persons", "AAA111 lists 3 person", variant(6), e)
    e = manifest_entries(variant(7), 10)
    e["BBB222"]["multiperson"] = ["CCC333"]
    case("partners-disagree", "BBB222 lists", variant(7), e)
    other = variant(8).replace("AAA111", "XXX999")
    e = manifest_entries(variant(8), 10)
    case("name-mismatch", "the name names XXX999 and BBB222", other, e)
    e = manifest_entries(variant(9), 10)
    e["AAA111"]["length"] = "10"
    case("malformed-entry", "'length' is '10'", variant(9), e)
    e = manifest_entries(variant(10), 10)
    del e["BBB222"]["audio"]
    case("malformed-entry", "entry for BBB222: no 'audio' field", variant(10), e)
    e = manifest_entries(variant(11), 10)
    e["AAA111"]["audio"] = "/elsewhere/track.wav"
    case("bad-audio-path", "'/elsewhere/track.wav' of AAA111", variant(11), e)
    e = manifest_entries(variant(12), 10)
    e["AAA111"]["multiperson"] = []
    case("not-two-persons", "AAA111 lists 1 person", variant(12), e)
    # Three- and four-person sequences of the other sections: their names parse (issue #19).
    for n, extra in ((13, ["CCC333"]), (14, ["CCC333", "DDD444"])):
        crowd = variant(n).replace("--BBB222--", "--BBB222--" + "--".join(extra) + "--")
        people = ["AAA111", "BBB222", *extra]
        entries = {p: {"length": 10, "id": 1, "text": "", "audio": None,
                       "multiperson": [q for q in people if q != p]} for p in people}
        case("not-two-persons", f"the name names {len(people)} persons", crowd, entries)

    first, second = tmp_path / "one", tmp_path / "two"
    manifest = write_manifest(first, {good: manifest_entries(good, 10),
                                      **{q: c[0] for q, c in cases.items()}})
    # The same sequence in a second folder: the first listing wins, the second is reported.
    second_manifest = write_manifest(second, {good: manifest_entries(good, 10)})
    corpus = read_corpus([first, second])
    assert corpus.problems == []
    assert [p.sequence for p in corpus.pairs] == [good]
    assert corpus.pairs[0].folder == first
    by_name = {(s.sequence, s.path): s for s in corpus.skipped}
    assert len(by_name) == len(corpus.skipped) == len(cases) + 1
    for name, (_, kind, reason) in cases.items():
        skip = by_name[(name, manifest)]
        assert skip.kind == kind, (name, skip)
        assert reason in skip.reason, (reason, skip.reason)
        assert str(skip).startswith(f"{manifest}: {name}: ")
    dup = by_name[(good, second_manifest)]
    assert dup.kind == "duplicate" and str(manifest) in dup.reason


def test_duplicate_keys_in_one_manifest(tmp_path):
    folder = tmp_path / "aiagent"
    q1, q2 = variant(1), variant(2)
    e1, e2 = manifest_entries(q1, 10), manifest_entries(q2, 10)
    dump = json.dumps
    # AAA111 lists q1 twice; BBB222 appears twice at the top level (q2 split across both).
    text = ("{" + f'"AAA111": {{{dump(q1)}: {dump(e1["AAA111"])}, {dump(q1)}: '
            f'{dump(e1["AAA111"])}, {dump(q2)}: {dump(e2["AAA111"])}}}, '
            f'"BBB222": {{{dump(q1)}: {dump(e1["BBB222"])}}}, '
            f'"BBB222": {{{dump(q2)}: {dump(e2["BBB222"])}}}' + "}")
    folder.mkdir()
    (folder / "dataset.json").write_text(text)
    corpus = read_corpus(folder)
    assert [p.sequence for p in corpus.pairs] == [q2]
    skip, = corpus.skipped
    assert (skip.sequence, skip.kind) == (q1, "duplicate")
    assert "listed more than once for AAA111" in skip.reason


def test_file_level_problems_do_not_stop_other_folders(tmp_path):
    good = tmp_path / "good"
    write_manifest(good, {variant(0): manifest_entries(variant(0), 10)})
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "dataset.json").write_text('{"AAA111": {"x": ')
    listy = tmp_path / "listy"
    listy.mkdir()
    (listy / "dataset.json").write_text("[]")
    binary = tmp_path / "binary"
    binary.mkdir()
    (binary / "dataset.json").write_bytes(b'{"\xff\xfe": 1}')
    odd_subject = tmp_path / "odd"
    write_manifest(odd_subject, {variant(1): manifest_entries(variant(1), 10)})
    data = json.loads((odd_subject / "dataset.json").read_text())
    data["ZZZ000"] = ["not", "an", "object"]
    (odd_subject / "dataset.json").write_text(json.dumps(data))
    empty = tmp_path / "empty"
    empty.mkdir()
    corpus = read_corpus([broken, good, tmp_path / "absent", listy, binary, empty,
                          odd_subject, good])
    assert [p.sequence for p in corpus.pairs] == [variant(0), variant(1)]
    lines = [str(p) for p in corpus.problems]
    expected = [
        (broken / "dataset.json", "not valid JSON (Expecting value at line 1, column 18)"),
        (tmp_path / "absent", "folder does not exist"),
        (listy / "dataset.json", "top level is a list"),
        (binary / "dataset.json", "not UTF-8 text"),
        (empty / "dataset.json", "missing dataset.json"),
        (odd_subject / "dataset.json", "subject 'ZZZ000' maps to a list"),
        (good, "folder given more than once"),
    ]
    assert len(lines) == len(expected)
    for line, (path, reason) in zip(lines, expected):
        assert line.startswith(f"{path}: {reason}"), line
        assert "\n" not in line


def test_person_files_paths_lists_every_file(tmp_path):
    pair, folder = _one_written_pair(tmp_path)
    for person in pair.persons:
        paths = pair.files[person].paths()
        assert len(paths) == len(SMPLX_PARAM_WIDTHS) + 2
        assert all(p.is_file() for p in paths)
        assert sorted(paths) == sorted(p for p in (folder / pair.sequence / person).rglob("*")
                                       if p.is_file())


def test_a_manifest_with_a_byte_order_mark_is_read(tmp_path):
    """Issue #19: a dataset.json saved with a UTF-8 BOM lost its whole section."""
    folder = tmp_path / "aiagent"
    name = variant(0)
    manifest = write_manifest(folder, {name: manifest_entries(name, 10)})
    manifest.write_bytes(b"\xef\xbb\xbf" + manifest.read_bytes())
    corpus = read_corpus(folder, require_audio=False)
    assert corpus.problems == [] and [p.sequence for p in corpus.pairs] == [name]


def test_scene_names_with_hyphens_parse():
    """Issue #19: a real dyad's scene is ..._Participating_in_a_High-Stakes_Heist_..."""
    name = BASE.replace("AIAGENT_scene_009",
                        "ACTING_Participating_in_a_High-Stakes_Heist_scene_001")
    parsed = parse_sequence_name(name)
    assert parsed.scene == "ACTING_Participating_in_a_High-Stakes_Heist_scene_001"
    assert parsed.named_persons == ("AAA111", "BBB222") and parsed.length == 10
    with pytest.raises(ValueError, match="does not match"):
        parse_sequence_name(BASE.replace("AIAGENT_scene_009", "bad--scene"))


def test_null_audio_with_files_on_disk_uses_them(tmp_path):
    """Upstream: audio missed in the upload is listed as null and added later. When the wavs are
    where they belong, the reader uses them and says so (#19 item 6)."""
    name = variant(20)
    entries = manifest_entries(name, 10, audio=False)
    write_manifest(tmp_path, {name: entries})
    write_sequence(tmp_path, name, audio=True)
    corpus = read_corpus(tmp_path)
    (pair,) = corpus.pairs
    assert pair.has_audio and len(pair.notes) == 2
    assert all("lists no audio" in note and "using it" in note for note in pair.notes)
    # Without the files it stays a sequence without audio.
    other = variant(21)
    write_manifest(tmp_path / "b", {other: manifest_entries(other, 10, audio=False)})
    write_sequence(tmp_path / "b", other, audio=False)
    corpus = read_corpus(tmp_path / "b")
    assert not corpus.pairs and corpus.skipped[0].kind == "no-audio"
