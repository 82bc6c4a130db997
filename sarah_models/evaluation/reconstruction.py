"""Reconstruction error per body part, in millimetres: how far the VAE's decoding of a window's
own motion lands from it.

Table 1's metrics score motion as a whole; a decoder that gives up on one part (the feet parked
at the data's mean, a head icosahedron blown up to twice its size) hides in them: foot slide
even improves when a foot never moves. Per joint group (``sarah_data.skeleton.JOINT_GROUPS``)
and window, two figures, means over frames and the group's joints:

* position: the distance between decoded and true joint positions (icosahedron centroids);
* orientation: the distance between decoded and true icosahedron vertices once each is taken
  relative to its own centroid -- the joint's rotation error (0.1 rad moves a vertex 10 mm at
  the 10 cm radius) plus any distortion of the icosahedron.

The shell points get one position row. Each figure is a mean over windows with a 95 % bootstrap
interval over windows (``metrics.table.bootstrap_interval``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sarah_data.skeleton import JOINT_GROUPS, MotionLayout

from .metrics.table import bootstrap_interval
from .tables import with_interval

SHELL = "shell"


def part_errors(decoded, truth, layout: MotionLayout) -> dict[str, tuple[float, float]]:
    """(T, Dx) decoded and true motion in metres -> {group: (position mm, orientation mm)};
    the shell's orientation is NaN (points have none)."""
    decoded_ico, decoded_shell = layout.split(np.asarray(decoded, dtype=np.float64))
    true_ico, true_shell = layout.split(np.asarray(truth, dtype=np.float64))
    decoded_centre, true_centre = decoded_ico.mean(-2), true_ico.mean(-2)
    position = np.linalg.norm(decoded_centre - true_centre, axis=-1)  # (T, J)
    offsets = ((decoded_ico - decoded_centre[..., None, :]) - (true_ico - true_centre[..., None, :]))
    orientation = np.linalg.norm(offsets, axis=-1).mean(-1)  # (T, J)
    out = {}
    for group, names in JOINT_GROUPS.items():
        joints = [layout.joint(n) for n in names if n in layout.joint_names]
        if joints:
            out[group] = (1000.0 * float(position[:, joints].mean()),
                          1000.0 * float(orientation[:, joints].mean()))
    if layout.shell_points:
        out[SHELL] = (1000.0 * float(np.linalg.norm(decoded_shell - true_shell, axis=-1).mean()), np.nan)
    return out


@dataclass
class ReconstructionErrors:
    """Per-window part errors, gathered as a producer's windows are decoded (``observe``)."""

    layout: MotionLayout
    windows: list[dict[str, tuple[float, float]]] = field(default_factory=list)

    def observe(self, produce):
        """Wrap a ``produce(item, index) -> motion`` so that every window it decodes is scored
        against the item's own motion on the way through (the VAE runs once)."""
        def observed(item: dict, index: int):
            motion = produce(item, index)
            self.windows.append(part_errors(motion, item["motion"], self.layout))
            return motion

        return observed

    def summary(self) -> dict[str, dict[str, float]]:
        """{group: {position, position_low, position_high, orientation, ...}} in mm."""
        out = {}
        for group in self.windows[0] if self.windows else ():
            row = {}
            for i, kind in enumerate(("position", "orientation")):
                values = np.array([w[group][i] for w in self.windows])
                if np.isnan(values).all():
                    continue
                low, high = bootstrap_interval(values)
                row.update({kind: float(values.mean()), f"{kind}_low": low, f"{kind}_high": high})
            out[group] = row
        return out



def summary_markdown(summary: dict[str, dict[str, float]], caption: str) -> str:
    """A ``ReconstructionErrors.summary()`` as a markdown table under ``caption``."""
    def cell(row: dict, kind: str) -> str:
        if kind not in row:
            return "-"
        return with_interval(row[kind], row[kind + "_low"], row[kind + "_high"], 1)

    lines = [caption, "", "| part | position error, mm | orientation error, mm |", "|---|---|---|"]
    lines += [f"| {group} | {cell(row, 'position')} | {cell(row, 'orientation')} |"
              for group, row in summary.items()]
    return "\n".join(lines) + "\n"
