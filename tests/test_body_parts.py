"""FGD_acc by body part (``metrics.body_parts``) on prepared fixture motion: the shell split into
parts where they are on the body, and a distance that lands in the part that differs."""

import json
from dataclasses import asdict

import numpy as np
import pytest

from sarah_data.constants import JOINT_NAMES
from sarah_data.dataset import WindowDataset
from sarah_data.skeleton import JOINT_GROUPS, MotionLayout, shell_parts
from sarah_models.evaluation.metrics import MetricsConfig, MetricsTable, evaluate
from sarah_models.evaluation.metrics.body_parts import part_key
from sarah_models.evaluation.tables import MethodResult, table1_markdown
from sarah_models.evaluation.windows import motion_clip


@pytest.fixture(scope="module")
def windows(prepared_shards):
    data = WindowDataset.sliding(prepared_shards, "train", extractor=None, window=64)
    items = [data[i] for i in range(0, len(data), max(1, len(data) // 8))][:8]
    layout = MotionLayout.from_width(data.motion_dim)
    return layout, [(item["motion"].numpy().astype(np.float64), item["user_head"].numpy())
                    for item in items]


def test_each_shell_point_goes_to_the_group_of_the_joint_nearest_it():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(len(JOINT_NAMES), 3)) * 0.5
    icosahedra = centres[:, None] + rng.normal(size=(len(JOINT_NAMES), 12, 3)) * 0.01
    names = ["left_knee", "right_foot", "head", "left_wrist", "left_index1", "pelvis", "right_ankle"]
    shell = np.stack([centres[JOINT_NAMES.index(name)] + 0.01 for name in names])
    parts = shell_parts(icosahedra, shell)
    assert parts == {"root": (5,), "spine and head": (2,), "legs": (0, 6), "feet": (1,),
                     "arms": (3,), "hands": (4,)}
    assert list(parts) == list(JOINT_GROUPS)  # the groups' own order
    without_hands = shell_parts(icosahedra, np.delete(shell, 4, axis=0))
    assert "hands" not in without_hands and without_hands["root"] == (4,)  # no point, no group


def test_every_shell_point_lands_in_one_part_where_that_part_is(windows):
    layout, clips = windows
    icosahedra, shell = layout.split(clips[0][0][0])
    parts = shell_parts(icosahedra, shell, layout.joint_names)
    everyone = np.concatenate([np.asarray(points) for points in parts.values()])
    assert sorted(everyone) == list(range(layout.shell_points))  # each point once
    assert list(parts) == [group for group in JOINT_GROUPS if group in parts]
    assert {"legs", "feet", "arms", "spine and head"} <= set(parts)
    height = {part: shell[list(points), 1].mean() for part, points in parts.items()}
    assert height["feet"] < 0.15 < height["legs"] < height["spine and head"]
    with pytest.raises(ValueError, match="one frame"):
        shell_parts(icosahedra[None], shell, layout.joint_names)


def test_a_difference_in_the_legs_is_scored_in_the_legs_alone(windows):
    """Noise on the legs' shell points only: the legs' FGD_acc and energy rise, every other
    part's distance is 0 and its energy ratio exactly 1; the whole-shell figure is unchanged
    by scoring the parts, and the table shows a row per method with every part."""
    layout, clips = windows
    icosahedra, shell = layout.split(clips[0][0][0])
    parts = shell_parts(icosahedra, shell, layout.joint_names)
    rng = np.random.default_rng(0)
    truth, noisy = [], []
    for motion, user in clips:
        truth.append(motion_clip(motion, user))
        moved = motion.copy()
        legs = layout.icosahedra_width + 3 * np.asarray(parts["legs"])
        columns = (legs[:, None] + np.arange(3)).ravel()
        moved[:, columns] += rng.normal(scale=0.005, size=(len(moved), len(columns)))
        noisy.append(motion_clip(moved, user))
    speaking = np.zeros(len(clips), bool)
    config = MetricsConfig(batch_clips=4, normalize_window=False, pooled_groups=3)
    plain = evaluate(noisy, truth, speaking, config=config)
    table = evaluate(noisy, truth, speaking, config=MetricsConfig(
        batch_clips=4, normalize_window=False, pooled_groups=3, shell_parts=parts))
    np.testing.assert_equal(asdict(table.values["fgd_acc"]), asdict(plain.values["fgd_acc"]))
    assert table.shell_parts == {part: list(points) for part, points in parts.items()}
    legs = table.values[part_key("legs")]
    assert legs.avg > 0 and legs.pooled > 0 and legs.low <= legs.avg <= legs.high
    assert legs.ratio > 1.5 and legs.ratio_low > 1
    for part in parts:
        if part != "legs":
            values = table.values[part_key(part)]
            assert values.avg == pytest.approx(0, abs=1e-6 * legs.avg)
            assert values.ratio == pytest.approx(1.0)
    assert table.distances() == ["fgd", "fgd_local", "fgd_acc"] + [part_key(p) for p in parts]
    written = json.loads(json.dumps(table.to_dict(), allow_nan=False))
    assert MetricsTable.from_dict(written).to_dict() == table.to_dict()  # table1.json's rows
    markdown = table1_markdown([MethodResult("jitter", "legs jittered", False, None, table)], "T")
    assert "by body part" in markdown
    row = next(line for line in markdown.splitlines() if line.startswith("| legs jittered |")
               and "; e " in line)
    assert row.count("; e ") == len(parts)
    with pytest.raises(ValueError, match="outside"):
        evaluate(noisy, truth, speaking, config=MetricsConfig(shell_parts={"legs": (10_000,)}))
