"""Choose a model's sampling settings (noise scale, guidance) on a tuning corpus, by a rule fixed
before the results are read (docs/results.md, thirty-seventh run):

    python scripts/choose_sampling.py tune/*/ --flags-to sampling.txt

Each folder is one `sarah-eval --methods gt,model` run on the same tuning windows at one
(--noise-scale, --cfg[, --guide][, --guidance-interval]). The chosen setting is the one whose
paired wrist speed and Head Ang. (the "Beside GT" table) lie nearest GT in units of issue #16's
tolerances, the larger of |wrists / GT - 1| / 0.20 and |Head Ang. - GT| / 0.05, among the
settings that keep #16's other item-2 figures (foot slide, bone length, frame-0 offset) within
theirs. Prints every setting's
figures as a markdown table; with --flags-to, writes the chosen setting as sarah-eval flags.

A test corpus of another seed then reports the chosen setting's figures: the tuning corpus's
intervals are optimistic for the setting chosen on it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from sarah_data.atomic import atomic_write_text
from sarah_models.config import StreamConfig
from sarah_models.nn.flow import MODALITIES

WRIST_TOLERANCE = 0.20  # #16 item 2: wrist speed within 20 % of GT's
HEAD_TOLERANCE = 0.05  # #16 item 3: Head Ang. (g = none) within 0.05 of GT's
FOOT_SLIDE_MARGIN = 0.01  # #16 item 2: foot slide <= GT's + 0.01
BONE_LENGTH_MAX = 2.0  # #16 item 2: bone-length error <= 2 % (p95)
FRAME0_MAX = 5.0  # #16 item 2: frame-0 pelvis offset <= 5 cm


@dataclass(frozen=True)
class Setting:
    """One evaluated (noise scale, guidance) and the figures the rule reads."""

    noise_scale: float
    cfg: float
    guide: tuple[str, ...]  # what guidance's unconditional pass drops
    interval: tuple[float, float]  # the flow times guidance applies at (StreamConfig's)
    windows: tuple[str, str, int]  # shards, split, how many windows: settings compare on one
    wrists: tuple[float, float, float]  # ratio to GT, its paired 95 % interval
    head: tuple[float, float, float]  # difference to GT, its paired 95 % interval
    foot_slide_gap: float
    bone_length: float
    frame0: float

    @property
    def distance(self) -> float:
        """How far from GT in tolerances: <= 1 meets items 2-3's wrists and head (point values)."""
        return max(abs(self.wrists[0] - 1) / WRIST_TOLERANCE, abs(self.head[0]) / HEAD_TOLERANCE)

    @property
    def guides_some(self) -> bool:
        """Guidance drops some modalities only (the default, and the paper, drops all)."""
        return set(self.guide) != set(MODALITIES)

    @property
    def guides_some_times(self) -> bool:
        """Guidance applies at some flow times only (the default, and the paper: all)."""
        return self.interval != StreamConfig.guidance_interval

    @property
    def name(self) -> str:
        guided = f", guiding {'+'.join(self.guide)}" if self.guides_some else ""
        lo, hi = self.interval
        timed = f", at {lo:g} <= tau < {hi:g}" if self.guides_some_times else ""
        return f"{self.noise_scale:g}, {self.cfg:g}{guided}{timed}"

    @property
    def flags(self) -> str:
        guided = f" --guide {','.join(self.guide)}" if self.guides_some else ""
        lo, hi = self.interval
        timed = f" --guidance-interval {lo:g},{hi:g}" if self.guides_some_times else ""
        return f"--noise-scale {self.noise_scale:g} --cfg {self.cfg:g}{guided}{timed}"

    @property
    def eligible(self) -> bool:
        return (self.foot_slide_gap <= FOOT_SLIDE_MARGIN and self.bone_length <= BONE_LENGTH_MAX
                and self.frame0 <= FRAME0_MAX)


def read_setting(folder: Path) -> Setting:
    """The model row of ``folder/table1.json`` beside its GT row; ValueError names what is wrong."""
    path = folder / "table1.json"
    try:
        table = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: cannot read ({error})") from None
    try:
        models = [row for row in table["rows"] if row["key"] == "model"]
        settings, count = table["settings"], int(table["num_windows"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: not a sarah-eval table1.json") from None
    if len(models) != 1:
        raise ValueError(f"{path}: needs exactly one 'model' row (sarah-eval --methods gt,model), "
                         f"found {len(models)}")
    shown = models[0]["shown"]

    def value(name: str) -> float:
        found = shown.get(name)
        if found is None or not math.isfinite(found):
            raise ValueError(f"{path}: no {name} (an evaluation without the GT row, or one from "
                             f"before the Beside GT table)")
        return float(found)

    def triple(metric: str, kind: str) -> tuple[float, float, float]:
        return tuple(value(f"{metric}/{kind}{end}") for end in ("", "_low", "_high"))

    return Setting(noise_scale=float(settings["noise_scale"]),
                   cfg=float(settings["cfg_scale"]),
                   # tables from before --guide guided every modality
                   guide=tuple(settings.get("guide", MODALITIES)),
                   # ... and at every flow time
                   interval=tuple(map(float, settings.get("guidance_interval",
                                                          StreamConfig.guidance_interval))),
                   windows=(str(settings["shards"]), str(settings["split"]), count),
                   wrists=triple("wrist_speed", "ratio"), head=triple("head_angle", "gap"),
                   foot_slide_gap=value("foot_slide/gap"), bone_length=value("bone_length/avg"),
                   frame0=value("frame0_offset/avg"))


def choose(settings: list[Setting]) -> Setting | None:
    """The eligible setting nearest GT (ties: the first given); None when none is eligible."""
    eligible = [s for s in settings if s.eligible]
    return min(eligible, key=lambda s: s.distance) if eligible else None


def markdown(settings: list[Setting], chosen: Setting | None) -> str:
    lines = ["| noise scale, CFG[, guided][, when] | wrists ÷ GT (paired) | Head Ang. − GT (paired) | "
             "distance (≤ 1 meets) | foot slide − GT | bone length % | frame-0 cm |",
             "|---|---|---|---|---|---|---|"]
    for s in settings:
        name = s.name
        if s is chosen:
            name = f"**{name} (chosen)**"
        lines.append(
            f"| {name} | {s.wrists[0]:.2f} ({s.wrists[1]:.2f}-{s.wrists[2]:.2f}) | "
            f"{s.head[0]:+.3f} ({s.head[1]:+.3f} to {s.head[2]:+.3f}) | {s.distance:.2f} | "
            f"{s.foot_slide_gap:+.3f} | {s.bone_length:.1f} | {s.frame0:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Choose the (noise scale, CFG[, guided modalities][, flow times]) whose wrists "
                    "and head lie nearest GT on a tuning corpus, from sarah-eval output folders.")
    parser.add_argument("folders", nargs="+", type=Path,
                        help="sarah-eval --methods gt,model output folders, one per setting")
    parser.add_argument("--flags-to", type=Path, default=None,
                        help="write the chosen setting here as sarah-eval flags")
    args = parser.parse_args(argv)
    settings = []
    for folder in args.folders:
        try:
            settings.append(read_setting(folder))
        except ValueError as error:
            print(f"choose_sampling: skipped {error}", file=sys.stderr)
    if not settings:
        print("choose_sampling: no setting could be read", file=sys.stderr)
        return 2
    windows = {s.windows for s in settings}
    if len(windows) > 1:
        print("choose_sampling: the folders evaluated different windows (shards, split, count: "
              f"{sorted(windows)}); compare settings on the same windows", file=sys.stderr)
        return 2
    chosen = choose(settings)
    print(markdown(settings, chosen))
    if chosen is None:
        print("choose_sampling: no setting keeps foot slide, bone length and frame-0 offset "
              "within #16's item 2", file=sys.stderr)
        return 1
    shards, split, count = chosen.windows
    print(f"chosen on {count} windows of {shards} ({split}): {chosen.flags} "
          f"(distance {chosen.distance:.2f})")
    if args.flags_to is not None:
        atomic_write_text(args.flags_to, chosen.flags + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
