"""Test helper: write sequences in the exact Embody 3D on-disk layout from arrays.

Tests only (the library's fixture writer is sarah_data/fixtures/layout.py). Manifests are
written the way upstream writes them: absolute paths of the producer's machine, which the
reader must rebase onto the folder it reads.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import soundfile as sf

from sarah_data.constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME, SMPLX_PARAM_WIDTHS

PRODUCER_ROOT = "/social_ai/datasets/opensource_v5/aiagent"
REAL_MANIFEST = Path("/work/shared/embody3d/aiagent_dataset.json")


def with_frame_range(sequence: str, start: int, length: int) -> str:
    """`sequence` renamed to cover frames start .. start+length-1 (zero-padded like upstream)."""
    head, _ = sequence.rsplit("--", 1)
    return f"{head}--{start:06d}-{start + length - 1:06d}"


def persons_of(sequence: str) -> tuple[str, str]:
    a, b = sequence.split("--")[3:5]
    return a, b


def manifest_entries(sequence: str, length: int, audio: bool = True,
                     audio_folder: str = "audio_separated") -> dict[str, dict]:
    """{subject: entry} for both persons of `sequence`, as upstream's dataset.json has them."""
    a, b = persons_of(sequence)
    entries = {}
    for i, (me, partner) in enumerate(((a, b), (b, a))):
        wav = f"{PRODUCER_ROOT}/{sequence}/{me}/{audio_folder}/{sequence}.wav"
        entries[me] = {"length": length, "id": i, "text": None, "multiperson": [partner],
                       "audio": wav if audio else None}
    return entries


def write_manifest(folder: Path, sequences: dict[str, dict[str, dict]]) -> Path:
    """Write {sequence: {subject: entry}} as dataset.json's {subject: {sequence: entry}}."""
    by_subject: dict[str, dict] = {}
    for sequence, entries in sequences.items():
        for subject, entry in entries.items():
            by_subject.setdefault(subject, {})[sequence] = entry
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "dataset.json"
    path.write_text(json.dumps(by_subject, indent=1))
    return path


def random_params(length: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Small float32 parameters keyed by folder name (plausible magnitudes, not a real pose)."""
    return {folder: (0.1 * rng.standard_normal((length, width))).astype(np.float32)
            for folder, width in SMPLX_PARAM_WIDTHS.items()}


def write_person(folder: Path, sequence: str, subject: str, params: dict[str, np.ndarray],
                 mask: np.ndarray, audio: np.ndarray | None,
                 audio_folder: str = "audio_separated", rate: int = AUDIO_SAMPLE_RATE) -> Path:
    """Write one person's arrays under `<folder>/<sequence>/<subject>/`; returns that folder."""
    base = folder / sequence / subject
    for name, array in {**params, "missing": mask}.items():
        (base / name).mkdir(parents=True, exist_ok=True)
        np.save(base / name / f"{sequence}.npy", array)
    if audio is not None:
        (base / audio_folder).mkdir(parents=True, exist_ok=True)
        sf.write(base / audio_folder / f"{sequence}.wav", audio, rate, subtype="FLOAT")
    return base


def write_sequence(folder: Path, sequence: str, seed: int = 0, audio: bool = True,
                   audio_folder: str = "audio_separated") -> dict[str, dict]:
    """Both persons of `sequence` with random arrays; returns {subject: {params, mask, audio}}."""
    start, end = map(int, re.search(r"--(\d+)-(\d+)$", sequence).groups())
    length = end - start + 1
    rng = np.random.default_rng(seed)
    written = {}
    for subject in persons_of(sequence):
        params = random_params(length, rng)
        mask = (rng.random(length) > 0.1).astype(np.float32)
        wave = (0.01 * rng.standard_normal(length * SAMPLES_PER_FRAME)).astype(np.float32) \
            if audio else None
        write_person(folder, sequence, subject, params, mask, wave, audio_folder)
        written[subject] = {"params": params, "mask": mask, "audio": wave}
    return written
