"""``sarah-prep --audit raw/``: what a corpus holds, per section, before anything is prepared.

The tracking mask's polarity (1 = good) comes from the upstream README alone, so the audit
measures what would reveal it inverted: the tracked fraction, and where non-finite parameters
fall (a real capture's NaNs are where tracking failed, i.e. in frames marked untracked). It also
reports audio length differences from ``length * 1600`` samples and the stored dtypes. Nothing is
written.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME
from .embody3d import SMPLX_PARAM_WIDTHS, read_corpus
from .loading import DataProblem, load_mask, load_npy, nonfinite_frames

TRACKED_WARNING = 0.5  # below this tracked fraction the mask may be read the wrong way round
NONFINITE_EVIDENCE = 10  # NaN/inf frames needed before where they fall says anything


@dataclass
class SectionAudit:
    name: str
    sequences: int = 0  # two-person sequences read
    skipped: int = 0  # entries the reader skips (any reason)
    frames: int = 0  # person-frames
    tracked: int = 0
    nonfinite_tracked: int = 0  # person-frames with a NaN/inf parameter, marked tracked
    nonfinite_untracked: int = 0
    audio_files: int = 0
    audio_off_samples: list[int] = field(default_factory=list)  # |samples - length*1600| per file
    dtypes: Counter = field(default_factory=Counter)
    problems: list[str] = field(default_factory=list)

    @property
    def tracked_fraction(self) -> float:
        return self.tracked / self.frames if self.frames else float("nan")

    def warnings(self) -> list[str]:
        out = []
        if self.frames and self.tracked_fraction < TRACKED_WARNING:
            out.append(f"{self.name}: only {100 * self.tracked_fraction:.0f} % of frames are marked "
                       f"tracked: is the mask inverted (1 = good tracking)?")
        bad = self.nonfinite_tracked + self.nonfinite_untracked
        if bad >= NONFINITE_EVIDENCE and self.nonfinite_tracked > self.nonfinite_untracked:
            out.append(f"{self.name}: {self.nonfinite_tracked} of {bad} frames with NaN/inf "
                       f"parameters are marked tracked: is the mask inverted?")
        return out


def audit(sections: list[Path], log=print) -> list[SectionAudit]:
    import soundfile as sf

    results = []
    for folder in sections:
        corpus = read_corpus([folder], require_audio=False)
        report = SectionAudit(folder.name, sequences=len(corpus.pairs), skipped=len(corpus.skipped))
        report.problems += [f"{p.path}: {p.reason}" for p in corpus.problems]
        for pair in corpus.pairs:
            for person in pair.persons:
                files = pair.files[person]
                try:
                    valid = load_mask(files.missing, pair.length)
                    bad = np.zeros(pair.length, bool)
                    for folder_name, width in SMPLX_PARAM_WIDTHS.items():
                        array = load_npy(files.params[folder_name], (width,), "f", pair.length,
                                         check_finite=False)
                        report.dtypes[f"{folder_name}: {array.dtype}"] += 1
                        bad[nonfinite_frames(array)] = True
                except DataProblem as problem:
                    report.problems.append(str(problem))
                    continue
                report.frames += pair.length
                report.tracked += int(valid.sum())
                report.nonfinite_tracked += int((bad & valid).sum())
                report.nonfinite_untracked += int((bad & ~valid).sum())
                if files.audio is not None and Path(files.audio).is_file():
                    try:
                        info = sf.info(str(files.audio))
                    except RuntimeError as error:
                        report.problems.append(f"{files.audio}: unreadable audio ({error})")
                        continue
                    report.audio_files += 1
                    samples = round(info.frames * AUDIO_SAMPLE_RATE / info.samplerate)
                    report.audio_off_samples.append(abs(samples - pair.length * SAMPLES_PER_FRAME))
                    report.dtypes[f"audio: {info.subtype} {info.samplerate} Hz {info.channels} ch"] += 1
        results.append(report)
        log(f"audited {folder.name}: {report.sequences} sequences")
    return results


def format_audit(results: list[SectionAudit]) -> str:
    lines = ["| section | sequences | skipped entries | person-frames | tracked | NaN/inf frames tracked / untracked | audio files | audio off by (samples, median / max) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        off = np.asarray(r.audio_off_samples or [0])
        lines.append(f"| {r.name} | {r.sequences} | {r.skipped} | {r.frames} | "
                     f"{100 * r.tracked_fraction:.1f} % | {r.nonfinite_tracked} / {r.nonfinite_untracked} | "
                     f"{r.audio_files} | {np.median(off):.0f} / {off.max():.0f} |")
    for r in results:
        lines.append(f"{r.name} dtypes: " + ", ".join(f"{k} x{v}" for k, v in sorted(r.dtypes.items())))
        lines += [f"warning: {w}" for w in r.warnings()]
        lines += [f"problem: {p}" for p in r.problems[:20]]
        if len(r.problems) > 20:
            lines.append(f"... and {len(r.problems) - 20} more problems in {r.name}")
    return "\n".join(lines)
