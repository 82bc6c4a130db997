"""Train/val/test splits by capture session (paper A.2: 80/10/10).

Splitting by session, not by subject as the upstream example loader does, keeps both partners of
a conversation, and every other conversation recorded in the same sitting, in one split.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import numpy as np

SPLITS = ("train", "val", "test")


def split_sessions(session_frames: dict[str, int], fractions=(0.8, 0.1, 0.1), seed: int = 0
                   ) -> dict[str, list[str]]:
    """Assign sessions to splits, aiming at `fractions` of the frames.

    Sessions are visited in a seeded random order. With three or more sessions, val and test first
    receive one session each (so a small corpus still has all three splits); every further session
    goes to the split furthest below its target. Deterministic for the same sessions and seed.
    """
    if len(fractions) != 3 or abs(sum(fractions) - 1.0) > 1e-6 or min(fractions) < 0:
        raise ValueError(f"split fractions must be three non-negative numbers summing to 1, got {fractions}")
    sessions = sorted(session_frames)
    order = [sessions[i] for i in np.random.default_rng(seed).permutation(len(sessions))]
    total = sum(session_frames.values())
    assigned: dict[str, list[str]] = {name: [] for name in SPLITS}
    frames = dict.fromkeys(SPLITS, 0)
    if len(order) >= 3:
        for name in ("val", "test"):
            if fractions[SPLITS.index(name)] > 0:
                session = order.pop(0)
                assigned[name].append(session)
                frames[name] += session_frames[session]
    for session in order:
        deficit = {name: fractions[i] * total - frames[name] for i, name in enumerate(SPLITS)}
        name = max(SPLITS, key=lambda n: (deficit[n], -SPLITS.index(n)))
        assigned[name].append(session)
        frames[name] += session_frames[session]
    return {name: sorted(assigned[name]) for name in SPLITS}


def session_frames_of(pairs: Iterable) -> dict[str, int]:
    frames: dict[str, int] = defaultdict(int)
    for pair in pairs:
        frames[pair.session] += pair.length
    return dict(frames)
