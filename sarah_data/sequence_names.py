"""Embody 3D sequence names: what a name says (session, date, the two subjects, scene, frames).

    c--YYYYMMDD--HHMM--<SUBJ>--<SUBJ>--pilot--MotionPrior[N]--<SCENE>--<start>-<end>
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime

# Two or more subjects (the dyadic section has two; other sections name three or four), and
# scenes whose words may be joined by single hyphens ("..._High-Stakes_Heist_...").
NAME_PATTERN = re.compile(
    r"(?P<session>c--(?P<date>\d{8})--(?P<time>\d{4}))"
    r"(?P<subjects>(?:--[A-Za-z0-9]+){2,}?)"
    r"--pilot--(?P<prior>MotionPrior\d*)"
    r"--(?P<scene>[A-Za-z0-9_]+(?:-[A-Za-z0-9_]+)*)"
    r"--(?P<start>\d+)-(?P<end>\d+)"
)
NAME_FORMAT = "c--YYYYMMDD--HHMM--<SUBJ>--<SUBJ>--pilot--MotionPrior[N]--<SCENE>--<start>-<end>"


@dataclass(frozen=True)
class SequenceName:
    """The fields encoded in an Embody 3D sequence name."""

    sequence: str
    session: str  # c--YYYYMMDD--HHMM: one capture session; split by this, never by subject
    recorded: datetime  # capture start, local time of the session (minute resolution)
    named_persons: tuple[str, ...]  # in the order the name lists them (two in a dyad)
    motion_prior: str
    scene: str
    start: int  # first frame (inclusive)
    end: int  # last frame (inclusive)

    @property
    def length(self) -> int:
        return self.end - self.start + 1


def parse_sequence_name(sequence: str) -> SequenceName:
    """Parse `c--YYYYMMDD--HHMM--<SUBJ>--<SUBJ>--pilot--MotionPrior[N]--<SCENE>--<start>-<end>`.

    Raises ValueError with the reason when the name does not follow the format.
    """
    m = NAME_PATTERN.fullmatch(sequence)
    if m is None:
        raise ValueError(f"does not match {NAME_FORMAT}")
    try:
        recorded = datetime.strptime(m["date"] + m["time"], "%Y%m%d%H%M")
    except ValueError:
        raise ValueError(f"invalid capture date/time {m['date']}--{m['time']}") from None
    persons = tuple(m["subjects"].split("--")[1:])
    twice = sorted({p for p in persons if persons.count(p) > 1})
    if twice:
        raise ValueError(f"names the same person twice ({', '.join(twice)})")
    start, end = int(m["start"]), int(m["end"])
    if end < start:
        raise ValueError(f"frame range {m['start']}-{m['end']} ends before it starts")
    return SequenceName(sequence, m["session"], recorded, persons, m["prior"], m["scene"],
                        start, end)
