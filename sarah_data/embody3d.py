"""Corpus reader for the dyadic sections of Embody 3D: section folders -> `Corpus` of pairs.

`read_corpus` reads only each folder's dataset.json (fast; no data file is opened), pairs the two
partners of every sequence, and reports everything it cannot use: sequences in `skipped` (with a
reason and a kind), unreadable manifests and folders in `problems`. Nothing is dropped silently.
Whether the data files exist is a separate step (`check_files`), and their contents are checked
when a person is loaded (`load_person`), which raises `DataProblem(path, reason)` for bad input.

On-disk layout of one section (see /work/shared/embody3d/README.md):

    <folder>/dataset.json                      {subject: {sequence: {length, id, text, multiperson, audio}}}
    <folder>/<sequence>/<SUBJ>/smplx_mesh_*/<sequence>.npy   (T, width) per SMPLX_PARAM_WIDTHS
    <folder>/<sequence>/<SUBJ>/missing/<sequence>.npy        (T,) 1 = good tracking, 0 = do not use
    <folder>/<sequence>/<SUBJ>/audio_separated/<sequence>.wav  (or separated_audio/), mono 48 kHz
"""

from __future__ import annotations

import json
import os
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path, PurePosixPath

import numpy as np

from sarah_data.constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME, SMPLX_PARAM_WIDTHS
from sarah_data.loading import (DataProblem, fill_nonfinite_frames, format_frames, load_mask, load_npy,
                                load_wav, nonfinite_frames)
from sarah_data.sequence_names import SequenceName, parse_sequence_name

__all__ = [
    "AUDIO_FOLDERS", "MASK_FOLDER", "PARAM_KEYS", "Corpus", "DataProblem", "PairRecord",
    "PersonArrays", "PersonFiles", "Problem", "SequenceName", "Skip", "check_files",
    "load_person", "parse_sequence_name", "read_corpus",
]

MANIFEST_NAME = "dataset.json"
# The manifest's paths say audio_separated/, the upstream README tree says separated_audio/.
AUDIO_FOLDERS = ("audio_separated", "separated_audio")
MASK_FOLDER = "missing"
# Folder name on disk -> key of the params dict handed to the body model.
PARAM_KEYS = {folder: folder.removeprefix("smplx_mesh_") for folder in SMPLX_PARAM_WIDTHS}

# ----------------------------------------------------------------------------- records

@dataclass(frozen=True)
class Problem:
    """A file or folder the reader could not use at all (not one sequence: a whole manifest)."""

    path: Path
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


@dataclass(frozen=True)
class Skip:
    """A sequence listed in a manifest but not turned into a pair, and why.

    `kind` is one of: no-audio, audio-mismatch, missing-partner, not-two-persons,
    partners-disagree, name-mismatch, malformed-name, malformed-entry, length-mismatch,
    bad-audio-path, duplicate.
    """

    sequence: str
    path: Path  # the dataset.json that lists it
    reason: str
    kind: str

    def __str__(self) -> str:
        return f"{self.path}: {self.sequence}: {self.reason}"


@dataclass(frozen=True)
class PersonFiles:
    """One person's files in one sequence (paths rebased onto the folder read)."""

    params: dict[str, Path]  # keyed by SMPLX_PARAM_WIDTHS folder names, e.g. smplx_mesh_betas
    missing: Path  # tracking mask
    audio: Path | None  # None only when read with require_audio=False and the manifest has none

    def paths(self) -> list[Path]:
        """Every file of this person: six parameter arrays, the mask, then the audio if any."""
        return [*self.params.values(), self.missing] + ([self.audio] if self.audio else [])


@dataclass(frozen=True)
class PairRecord:
    """One two-person sequence."""

    sequence: str
    folder: Path  # the section folder it was read from
    session: str
    recorded: datetime
    scene: str
    start: int
    end: int
    length: int  # frames at 30 fps; == end - start + 1
    persons: tuple[str, str]  # sorted subject ids
    files: dict[str, PersonFiles]  # keyed by subject id
    notes: tuple[str, ...] = ()  # what the reader did beyond the manifest (e.g. audio found on disk)

    @property
    def has_audio(self) -> bool:
        return all(f.audio is not None for f in self.files.values())


@dataclass
class Corpus:
    """Everything `read_corpus` found: usable pairs, skipped sequences, unreadable files."""

    pairs: list[PairRecord] = field(default_factory=list)  # sorted by sequence name
    skipped: list[Skip] = field(default_factory=list)  # sorted by sequence name, then path
    problems: list[Problem] = field(default_factory=list)  # in the order met

    @property
    def sessions(self) -> list[str]:
        """Sorted unique capture sessions of the pairs."""
        return sorted({p.session for p in self.pairs})

    @property
    def subjects(self) -> list[str]:
        return sorted({s for p in self.pairs for s in p.persons})

    @property
    def skipped_by_kind(self) -> dict[str, int]:
        return dict(sorted(Counter(s.kind for s in self.skipped).items()))

    @property
    def counts(self) -> dict[str, int]:
        return {
            "pairs": len(self.pairs),
            "sessions": len(self.sessions),
            "subjects": len(self.subjects),
            "frames": sum(p.length for p in self.pairs),
            "skipped": len(self.skipped),
            "problems": len(self.problems),
        }

    def pair(self, sequence: str) -> PairRecord:
        for p in self.pairs:
            if p.sequence == sequence:
                return p
        raise KeyError(f"sequence {sequence!r} is not among the corpus's pairs")


# ----------------------------------------------------------------------------- reading

class _Pairs(list):
    """A JSON object kept as its (key, value) list, so repeated keys stay visible."""


class _SkipSequence(Exception):
    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind, self.reason = kind, reason


@dataclass(frozen=True)
class _Entry:
    length: int
    partners: tuple[str, ...]
    audio: str | None


def read_corpus(folders: list[Path] | Path | str, *, require_audio: bool = True) -> Corpus:
    """Read one or more section folders (each with a dataset.json) into a `Corpus`.

    Only the manifests are read; see `check_files` and `load_person` for the data files. A
    sequence listed in several folders is taken from the first folder given; the later
    listings are skipped as duplicates. With `require_audio=False`, sequences without audio are
    kept as pairs with `audio=None` instead of being skipped.
    """
    if isinstance(folders, (str, os.PathLike)):
        folders = [folders]
    corpus = Corpus()
    read_folders: set[Path] = set()
    first_listing: dict[str, Path] = {}
    for folder in map(Path, folders):
        if folder.resolve() in read_folders:
            corpus.problems.append(Problem(folder, "folder given more than once; read once"))
            continue
        read_folders.add(folder.resolve())
        manifest = folder / MANIFEST_NAME
        listing = _read_manifest(folder, manifest, corpus.problems)
        for sequence, entries in sorted((listing or {}).items()):
            if sequence in first_listing:
                corpus.skipped.append(Skip(
                    sequence, manifest, f"duplicate: already listed in {first_listing[sequence]}"
                    " (only the first listing is read)", "duplicate"))
                continue
            first_listing[sequence] = manifest
            try:
                corpus.pairs.append(_make_pair(folder, sequence, entries, require_audio))
            except _SkipSequence as skip:
                corpus.skipped.append(Skip(sequence, manifest, skip.reason, skip.kind))
    corpus.pairs.sort(key=lambda p: p.sequence)
    corpus.skipped.sort(key=lambda s: (s.sequence, str(s.path)))
    return corpus


def _read_manifest(folder: Path, manifest: Path, problems: list[Problem]
                   ) -> dict[str, list[tuple[str, object]]] | None:
    """sequence -> [(subject, raw entry), ...] in file order, or None (with a problem)."""
    if not folder.is_dir():
        problems.append(Problem(folder, "folder does not exist" if not folder.exists()
                                else "not a folder"))
        return None
    if not manifest.is_file():
        problems.append(Problem(manifest, "missing dataset.json"))
        return None
    try:
        # utf-8-sig: a manifest saved with a byte-order mark is still the same JSON
        top = json.loads(manifest.read_bytes().decode("utf-8-sig"), object_pairs_hook=_Pairs)
    except UnicodeDecodeError as err:
        problems.append(Problem(manifest, f"not UTF-8 text ({err.reason} at byte {err.start})"))
        return None
    except json.JSONDecodeError as err:
        problems.append(Problem(manifest, f"not valid JSON ({err.msg} at line {err.lineno}, "
                                          f"column {err.colno})"))
        return None
    except OSError as err:
        problems.append(Problem(manifest, f"unreadable ({err.strerror or err})"))
        return None
    if not isinstance(top, _Pairs):
        problems.append(Problem(manifest, f"top level is a {type(top).__name__}; expected an "
                                          "object {subject: {sequence: entry}}"))
        return None
    listing: dict[str, list[tuple[str, object]]] = defaultdict(list)
    for subject, sequences in top:
        if not isinstance(sequences, _Pairs):
            problems.append(Problem(manifest, f"subject {subject!r} maps to a "
                                              f"{type(sequences).__name__}; expected an object "
                                              "of sequences (its entries are ignored)"))
            continue
        for sequence, entry in sequences:
            listing[sequence].append((subject, entry))
    return listing


def _parse_entry(subject: str, raw: object) -> _Entry:
    def bad(why: str) -> _SkipSequence:
        return _SkipSequence("malformed-entry", f"entry for {subject}: {why}")

    if not isinstance(raw, _Pairs):
        raise bad(f"is a {type(raw).__name__}, expected an object")
    keys = [k for k, _ in raw]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise bad(f"key(s) {', '.join(map(repr, repeated))} given more than once")
    entry = dict(raw)
    for key in ("length", "multiperson", "audio"):
        if key not in entry:
            raise bad(f"no {key!r} field")
    length, partners, audio = entry["length"], entry["multiperson"], entry["audio"]
    if isinstance(length, bool) or not isinstance(length, int) or length < 0:
        raise bad(f"'length' is {length!r}, expected a non-negative integer")
    if partners is None:
        partners = []
    if not isinstance(partners, list) or not all(isinstance(p, str) for p in partners):
        raise bad(f"'multiperson' is {partners!r}, expected a list of subject ids")
    if audio is not None and not isinstance(audio, str):
        raise bad(f"'audio' is {audio!r}, expected a path or null")
    return _Entry(length, tuple(partners), audio)


def _make_pair(folder: Path, sequence: str, listed: list[tuple[str, object]],
               require_audio: bool) -> PairRecord:
    try:
        name = parse_sequence_name(sequence)
    except ValueError as err:
        raise _SkipSequence("malformed-name", f"malformed sequence name: {err}") from None
    if len(name.named_persons) != 2:
        raise _SkipSequence("not-two-persons", f"the name names {len(name.named_persons)} "
                                               f"persons ({', '.join(name.named_persons)}); need 2")
    subjects = [s for s, _ in listed]
    twice = sorted({s for s in subjects if subjects.count(s) > 1})
    if twice:
        raise _SkipSequence("duplicate", f"listed more than once for {', '.join(twice)}")
    entries = {s: _parse_entry(s, raw) for s, raw in listed}
    if len(entries) > 2:
        raise _SkipSequence("not-two-persons", f"listed for {len(entries)} subjects "
                                               f"({', '.join(subjects)}); need exactly 2")
    for subject, entry in entries.items():
        persons = {subject, *entry.partners}
        if len(persons) != 2:
            raise _SkipSequence("not-two-persons", f"{subject} lists {len(persons)} person(s) "
                                                   f"({', '.join(sorted(persons))}); need exactly 2")
    if len(entries) == 1:
        (subject, entry), = entries.items()
        raise _SkipSequence("missing-partner", f"no entry for partner {entry.partners[0]} "
                                               f"(listed by {subject})")
    (s1, e1), (s2, e2) = sorted(entries.items())
    if e1.partners != (s2,) or e2.partners != (s1,):
        raise _SkipSequence("partners-disagree", f"{s1} lists partners {list(e1.partners)}, "
                                                 f"{s2} lists {list(e2.partners)}")
    if {s1, s2} != set(name.named_persons):
        raise _SkipSequence("name-mismatch", f"entries are for {s1} and {s2}, the name "
                                             f"names {' and '.join(name.named_persons)}")
    if e1.length != e2.length:
        raise _SkipSequence("length-mismatch", f"persons disagree on length: {s1} {e1.length}, "
                                               f"{s2} {e2.length}")
    if e1.length != name.length:
        raise _SkipSequence("length-mismatch", f"length {e1.length} in dataset.json, but the "
                                               f"name's frame range {name.start}-{name.end} "
                                               f"gives {name.length}")
    # "audio": null may mean "missed in the upload, to be added later" (upstream): files that are
    # on disk where the audio belongs are used, and said so.
    found = {s: _unlisted_audio(folder, sequence, s) for s, e in ((s1, e1), (s2, e2)) if e.audio is None}
    notes = tuple(f"{sequence}/{s}: dataset.json lists no audio, but {path} is there; using it"
                  for s, path in sorted(found.items()) if path is not None)
    e1, e2 = (replace(e, audio=str(found[s])) if found.get(s) is not None else e
              for s, e in ((s1, e1), (s2, e2)))
    if (e1.audio is None) != (e2.audio is None):
        has, lacks = (s1, s2) if e2.audio is None else (s2, s1)
        raise _SkipSequence("audio-mismatch", f"audio listed for {has} but not for {lacks}")
    if e1.audio is None and require_audio:
        raise _SkipSequence("no-audio", "no audio (audio is null in dataset.json)")
    files = {s: _person_files(folder, sequence, s, e.audio) for s, e in ((s1, e1), (s2, e2))}
    return PairRecord(sequence=sequence, folder=folder, session=name.session,
                      recorded=name.recorded, scene=name.scene, start=name.start, end=name.end,
                      length=name.length, persons=(s1, s2), files=files, notes=notes)


def _unlisted_audio(folder: Path, sequence: str, subject: str) -> Path | None:
    """The wav a null manifest entry would have listed, when it is on disk."""
    path = _existing_audio(folder / sequence / subject / AUDIO_FOLDERS[0] / f"{sequence}.wav")
    return path if path.is_file() else None


def _person_files(folder: Path, sequence: str, subject: str, audio: str | None) -> PersonFiles:
    base = folder / sequence / subject
    params = {f: base / f / f"{sequence}.npy" for f in SMPLX_PARAM_WIDTHS}
    audio_path = None if audio is None else _existing_audio(
        _rebase_audio(folder, sequence, subject, audio))
    return PersonFiles(params=params, missing=base / MASK_FOLDER / f"{sequence}.npy",
                       audio=audio_path)


def _rebase_audio(folder: Path, sequence: str, subject: str, audio: str) -> Path:
    """The producer's absolute `.../<sequence>/<SUBJ>/<audio folder>/<file>.wav` under `folder`."""
    tail = PurePosixPath(audio).parts[-4:]
    if len(tail) == 4 and tail[:2] == (sequence, subject) and tail[2] in AUDIO_FOLDERS \
            and tail[3].endswith(".wav"):
        return folder.joinpath(*tail)
    raise _SkipSequence("bad-audio-path", f"audio path {audio!r} of {subject} is not "
                                          f"<...>/{sequence}/{subject}/"
                                          f"{{{','.join(AUDIO_FOLDERS)}}}/<file>.wav")


def _existing_audio(path: Path) -> Path:
    """`path`, or the same file under the other audio folder spelling if only that exists."""
    if path.exists():
        return path
    for spelling in AUDIO_FOLDERS:
        candidate = path.parent.parent / spelling / path.name
        if candidate.exists():
            return candidate
    return path


def check_files(corpus: Corpus) -> list[Problem]:
    """One `Problem` per data file of the corpus's pairs that is not on disk (contents unread)."""
    problems = []
    for pair in corpus.pairs:
        for person in pair.persons:
            files = pair.files[person]
            for path in [*files.params.values(), files.missing]:
                if not path.is_file():
                    problems.append(Problem(path, "missing file"))
            if files.audio is not None:
                audio = _existing_audio(files.audio)
                if not audio.is_file():
                    problems.append(Problem(audio, _missing_audio_reason(audio)))
    return problems


def _missing_audio_reason(path: Path) -> str:
    others = [f"{s}/" for s in AUDIO_FOLDERS if s != path.parent.name]
    return f"missing file (also looked in {', '.join(others)})"


# ----------------------------------------------------------------------------- loading

@dataclass
class PersonArrays:
    """One person's arrays for one sequence, checked against the manifest."""

    sequence: str
    person: str
    params: dict[str, np.ndarray]  # betas (T,300), body_pose (T,63), global_orient (T,3), ...
    valid: np.ndarray  # (T,) bool: True = good tracking
    audio: np.ndarray | None  # (T*1600,) float32 at 48 kHz
    warnings: list[str] = field(default_factory=list)
    # Frames with NaN/inf parameters: "tracked" ones were marked untracked, "untracked" ones were
    # untracked already (both filled with finite values).
    nonfinite: dict[str, int] = field(default_factory=lambda: {"tracked": 0, "untracked": 0})

    @property
    def length(self) -> int:
        return int(self.valid.shape[0])


def load_person(pair: PairRecord, person: str) -> PersonArrays:
    """Load and check one person's parameters, tracking mask and audio.

    Parameter arrays are read-only memory maps in their stored float dtype. Audio at another
    plausible rate is resampled to 48 kHz, and audio within one frame (1600 samples) of
    `length * 1600` is padded or trimmed to it; both add a line to `warnings`. Anything else
    wrong raises `DataProblem(path, reason)`.
    """
    if person not in pair.files:
        raise ValueError(f"{person!r} is not a person of {pair.sequence} "
                         f"(persons: {', '.join(pair.persons)})")
    files = pair.files[person]
    params = {PARAM_KEYS[folder]: load_npy(files.params[folder], (width,), "f", pair.length,
                                           check_finite=False)
              for folder, width in SMPLX_PARAM_WIDTHS.items()}
    valid = load_mask(files.missing, pair.length)
    audio, warnings = None, []
    # Untracked frames may hold anything (upstream promises nothing there); a NaN or inf in a
    # tracked frame makes that frame untracked instead of costing the whole sequence. Either
    # way the values are replaced by the nearest earlier finite frame, so every array is finite.
    counts = {"tracked": 0, "untracked": 0}
    for folder in SMPLX_PARAM_WIDTHS:
        key = PARAM_KEYS[folder]
        bad = nonfinite_frames(params[key])
        if not bad.size:
            continue
        tracked = bad[valid[bad]]
        counts["tracked"] += int(tracked.size)
        counts["untracked"] += int(bad.size - tracked.size)
        if tracked.size:
            valid = valid.copy()
            valid[tracked] = False
            warnings.append(f"{files.params[folder]}: NaN/inf in tracked frames {format_frames(tracked)}; "
                            f"those frames are marked untracked")
        params[key] = fill_nonfinite_frames(params[key], bad)
    if files.audio is not None:
        path = _existing_audio(files.audio)
        if not path.exists():
            raise DataProblem(path, _missing_audio_reason(path))
        audio, audio_warnings = load_wav(path, AUDIO_SAMPLE_RATE, pair.length * SAMPLES_PER_FRAME,
                                         tolerance=SAMPLES_PER_FRAME)
        warnings += audio_warnings
    return PersonArrays(pair.sequence, person, params, valid, audio, warnings, counts)
