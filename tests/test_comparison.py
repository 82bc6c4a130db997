"""Two evaluations of the same windows compared window by window (evaluation.comparison and
scripts/compare_evaluations.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import load_script
from sarah_models.evaluation.comparison import ComparisonError, compare
from sarah_models.evaluation.metrics import MetricsConfig, evaluate, frechet_distance
from sarah_models.evaluation.metrics.table import MetricsTable
from sarah_models.evaluation.tables import MethodResult
from test_metrics import _random_clip

compare_script = load_script("compare_evaluations")

CLIPS, GROUPS = 12, 4
CONFIG = MetricsConfig(batch_clips=4, pooled_groups=GROUPS)


def rows(turn_a: float, turn_b: float, scale_a: float = 0.06, scale_b: float = 0.06):
    """GT clips whose heads face the user at widely different angles (what windows share), and
    two generators that turn every head a little further, by ``turn_a`` and ``turn_b``, with
    shell noise of their own scale."""
    rng = np.random.default_rng(3)
    facings = np.linspace(0.0, 1.4, CLIPS)
    gt = [_random_clip(rng, facing=f) for f in facings]
    a = [_random_clip(rng, facing=f + turn_a, scale=scale_a) for f in facings]
    b = [_random_clip(rng, facing=f + turn_b, scale=scale_b) for f in facings]
    speaking = np.zeros(CLIPS, bool)
    return gt, evaluate(a, gt, speaking, config=CONFIG), evaluate(b, gt, speaking, config=CONFIG), a, b


def find(differences, name, column="avg"):
    return next(d for d in differences if d.name == name and d.column == column)


def test_a_row_against_itself_differs_by_nothing():
    _, a, _, _, _ = rows(0.1, 0.1)
    for d in compare(a, a):
        assert d.gap == 0 and not d.separated
        assert d.gap_low == pytest.approx(0, abs=1e-12) and d.gap_high == pytest.approx(0, abs=1e-12)
        assert math.isnan(d.ratio) or d.ratio == pytest.approx(1)


def test_pairing_separates_what_the_rows_own_intervals_cannot():
    """The heads of both rows spread over the same wide range (the windows'), and B turns each
    one 0.1 rad further than A: the rows' intervals overlap, their paired difference does not
    reach 0."""
    _, a, b, _, _ = rows(0.05, 0.15)
    own_a, own_b = a.values["head_angle"], b.values["head_angle"]
    assert own_a.low < own_b.high and own_b.low < own_a.high  # overlapping on their own
    d = find(compare(a, b), "head_angle")
    assert d.gap == pytest.approx(own_a.avg - own_b.avg) and d.gap > 0
    assert d.separated and 0 < d.gap_low <= d.gap <= d.gap_high


def test_pooled_difference_is_the_jackknife_of_the_left_out_differences():
    """Recomputed from the raw samples: each group of consecutive clips left out of both rows
    (and their ground truth) in turn, the difference of the two distances."""
    gt, a, b, clips_a, clips_b = rows(0.0, 0.0, scale_a=0.05, scale_b=0.09)
    groups = [[i for i in range(CLIPS) if i * GROUPS // CLIPS == g] for g in range(GROUPS)]

    def flat(clips, idx):
        return np.concatenate([clips[i].shell.reshape(len(clips[i].shell), -1) for i in idx])

    def distance(clips, idx):
        return frechet_distance(flat(clips, idx), flat(gt, idx)) * 1e4  # cm^2

    rests = [[i for i in range(CLIPS) if i not in g] for g in groups]
    left_a = np.array([distance(clips_a, rest) for rest in rests])
    left_b = np.array([distance(clips_b, rest) for rest in rests])
    assert a.per_group["fgd"] == pytest.approx(list(left_a), rel=1e-8)
    delta = left_a - left_b
    spread = 1.96 * np.sqrt((GROUPS - 1) / GROUPS * np.sum((delta - delta.mean()) ** 2))
    d = find(compare(a, b), "fgd", "pooled")
    assert d.gap == pytest.approx(distance(clips_a, range(CLIPS)) - distance(clips_b, range(CLIPS)),
                                  rel=1e-8)
    assert (d.gap_low, d.gap_high) == (pytest.approx(d.gap - spread, rel=1e-6),
                                       pytest.approx(d.gap + spread, rel=1e-6))
    assert d.gap < 0 and d.separated  # the quieter shell is nearer, pair by pair
    avg = find(compare(a, b), "fgd")  # Avg: the batches, paired
    assert avg.gap == pytest.approx(np.mean(a.per_batch["fgd"]) - np.mean(b.per_batch["fgd"]))
    assert len(a.per_batch["fgd"]) == CLIPS // CONFIG.batch_clips


def test_kept_values_survive_the_json_round_trip_and_old_rows_are_refused():
    gt, a, b, clips_a, _ = rows(0.05, 0.15)
    again = MetricsTable.from_dict(json.loads(json.dumps(a.to_dict())))
    assert again.per_clip["head_angle"] == pytest.approx(a.per_clip["head_angle"])
    assert [d.gap for d in compare(again, b)] == pytest.approx([d.gap for d in compare(a, b)])
    old = a.to_dict()
    for kept in ("per_batch", "per_group", "per_clip"):
        del old[kept]
    with pytest.raises(ComparisonError, match="per-window values"):
        compare(MetricsTable.from_dict(old), b)
    other = evaluate(clips_a, gt, np.zeros(CLIPS, bool), config=MetricsConfig(batch_clips=3))
    with pytest.raises(ComparisonError, match="batch-clips"):
        compare(other, b)


def write_eval(folder, table, key="model", windows=None):
    folder.mkdir()
    row = MethodResult(key, "Model", True, None, table)
    (folder / "table1.json").write_text(json.dumps({"rows": [row.to_dict()]}))
    listing = windows or [{"sequence": f"s{i}", "agent": "p", "start": 0} for i in range(CLIPS)]
    (folder / "windows.json").write_text(json.dumps({"windows": listing}))
    return folder


def test_script_prints_the_table_and_refuses_other_windows_in_one_line(tmp_path, capsys):
    _, a, b, _, _ = rows(0.05, 0.15)
    first, second = write_eval(tmp_path / "a", a), write_eval(tmp_path / "b", b)
    out = tmp_path / "cmp.md"
    assert compare_script.main([str(first), f"{second}:model", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text == out.read_text() and "12 windows" in text
    line = next(l for l in text.splitlines() if l.startswith("| Head Ang."))
    assert line.endswith("| yes |")
    moved = write_eval(tmp_path / "c", b, windows=[{"sequence": "x", "agent": "p", "start": 0}])
    assert compare_script.main([str(first), str(moved)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "different windows" in error
    assert compare_script.main([f"{first}:vae", str(second)]) == 2
    error = capsys.readouterr().err
    assert "table1.json: no row 'vae'" in error and error.count("\n") == 1


def test_script_reads_a_vae_runs_only_row_and_asks_for_a_key_among_several(tmp_path, capsys):
    _, a, b, _, _ = rows(0.05, 0.15)
    gt = MethodResult("gt", "GT", False, None, a, reference=True)
    folder = tmp_path / "vae"
    folder.mkdir()
    rows_of = lambda *keys: json.dumps({"rows": [gt.to_dict()] + [
        MethodResult(k, k.upper(), True, None, a).to_dict() for k in keys]})
    (folder / "table1.json").write_text(rows_of("vae"))
    (folder / "windows.json").write_text(json.dumps({"windows": [
        {"sequence": f"s{i}", "agent": "p", "start": 0} for i in range(CLIPS)]}))
    model = write_eval(tmp_path / "model", b)
    assert compare_script.main([str(folder), str(model)]) == 0
    implicit = capsys.readouterr().out
    assert compare_script.main([f"{folder}:vae", str(model)]) == 0
    explicit = capsys.readouterr().out
    assert implicit.startswith("A = VAE (") and implicit == explicit.replace(f"{folder}:vae", str(folder))
    (folder / "table1.json").write_text(rows_of("vae", "random"))
    assert compare_script.main([str(folder), str(model)]) == 2
    error = capsys.readouterr().err
    assert "no row 'model' and 2 others (rows: gt, vae, random)" in error and "FOLDER:KEY" in error
    assert error.count("\n") == 1
