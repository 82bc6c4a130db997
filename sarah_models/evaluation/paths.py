"""Where each method's agent walks: top views of its pelvis path in a few test windows.

FGD scores where the body is as one spread of positions; a picture of the paths shows what the
spread hides: an agent that walks where the data's stands, or walks to the user instead of
around them. The windows drawn are those where the user walks most and least (by the length
of the user's floor path), so both sides of the conversation's spatial story are shown.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from sarah_data.skeleton import ROOT, MotionLayout

from ..generation.plots import save_figure
from .metrics.clips import as_numpy, step_lengths


def floor_path_length(xz: np.ndarray) -> float:
    """Length of a floor path (T, 2), in its units."""
    return float(step_lengths(xz).sum())


def pick_windows(user_travel: Sequence[float], each: int = 3) -> list[int]:
    """Indices of the ``each`` windows where the user walks most, then the ``each`` where the
    user walks least (fewer when there are fewer windows; none twice)."""
    order = [int(i) for i in np.argsort(-np.asarray(user_travel, np.float64), kind="stable")]
    most = order[:each]
    least = [i for i in reversed(order) if i not in most][:each]
    return most + least


def recording(produce: Callable, indices: Sequence[int], layout: MotionLayout
              ) -> tuple[Callable, dict[int, np.ndarray]]:
    """``produce(item, index) -> motion`` wrapped to keep the pelvis floor path (T, 2) of the
    windows in ``indices`` as the method produces them, and the dict (window index -> path) it
    fills."""
    chosen, paths = set(int(i) for i in indices), {}

    def recorded(item, index: int):
        motion = produce(item, index)
        if index in chosen:
            joints = layout.joint_positions(np.asarray(as_numpy(motion), np.float64), [ROOT])
            paths[index] = joints[:, 0, [0, 2]]
        return motion

    return recorded, paths


def plot_paths(path: Path, user_heads: Mapping[int, np.ndarray],
               rows: Sequence[tuple[str, Mapping[int, np.ndarray]]]) -> Path:
    """One panel per window: the user's head (thin blue) and each row's pelvis path, the first
    row (the ground truth) in black; the agent starts at the origin of the window frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    windows = list(user_heads)
    columns = min(3, max(1, len(windows)))
    count_rows = -(-len(windows) // columns)
    fig, axes = plt.subplots(count_rows, columns, figsize=(4.2 * columns, 4.2 * count_rows),
                             squeeze=False)
    colours = ["k", "tab:red", "tab:orange", "tab:purple", "tab:brown", "tab:olive"]
    for ax, index in zip(axes.ravel(), windows):
        head = np.asarray(user_heads[index], np.float64)
        ax.plot(head[:, 0], head[:, 1], color="tab:blue", lw=1, label="user's head")
        for (label, paths), colour in zip(rows, colours):
            if index in paths:
                xz = paths[index]
                ax.plot(xz[:, 0], xz[:, 1], color=colour, lw=2 if colour == "k" else 1.2,
                        label=f"{label} ({floor_path_length(xz):.1f} m)")
        ax.plot([0], [0], "o", color="0.3", ms=4)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.set_title(f"window {index}: the user walks {floor_path_length(head):.1f} m",
                     fontsize=9)
        ax.legend(fontsize=6, loc="best")
    for ax in axes.ravel()[len(windows):]:
        ax.axis("off")
    fig.suptitle("Pelvis paths on the floor (x, z in m; the agent starts at the dot)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
