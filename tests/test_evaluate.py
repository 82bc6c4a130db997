"""sarah-eval: window selection, table formatting and the command end to end on tiny shards."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, strategies as st
from PIL import Image

from sarah_cli.eval import main
from helpers import load_script, write_split_shards
from sarah_models.training.checkpoint import load_checkpoint, save_checkpoint
from sarah_models.evaluation.degradations import blurred, jittered
from sarah_models.evaluation.runner import EvalConfig, EvalError, select_windows
from sarah_models.evaluation.tables import MethodResult, table1_markdown, table2_markdown
from sarah_models.evaluation.metrics import METRICS, CategoryValues, MetricsConfig, MetricsTable
from test_generate import save_run

plot_parts_script = load_script("plot_parts")

WINDOW = 16  # frames per evaluation window (a multiple of the tiny VAE's stride 4)


# --------------------------------------------------------------------------- windows


@given(available=st.integers(0, 500), requested=st.integers(1, 300))
def test_select_windows_all_or_evenly_spaced(available, requested):
    chosen = select_windows(available, requested)
    assert len(chosen) == min(available, requested)
    assert np.all(np.diff(chosen) > 0) and (available == 0 or chosen.max() < available)
    if available > requested > 1:
        assert chosen[0] == 0 and chosen[-1] == available - 1  # spans the whole split
        gaps = np.diff(chosen)
        assert gaps.max() - gaps.min() <= 1


# --------------------------------------------------------------------------- tables


def table(values: dict[str, tuple[float, float, float]], speaking=3, clips=10) -> MetricsTable:
    cfg = MetricsConfig()
    return MetricsTable(values={k: CategoryValues(*v) for k, v in values.items()},
                        units={k: "u" for k in METRICS}, display_scale=dict(cfg.display_scale),
                        num_clips=clips, num_speaking=speaking, num_non_speaking=clips - speaking,
                        window_frames=400, fps=30.0, batch_clips=16, num_batches=1)


RAW = {"fgd": (12.8, 3.5, 8.7), "fgd_acc": (2.19e5, 0.01e5, 7.81e5),
       "foot_slide": (0.01, 0.012, math.nan), "wrist_speed": (105.04, 90.1, 146.2),
       "head_angle": (0.83, 0.82, 0.85)}


def test_table1_markdown_columns_scales_and_dashes():
    gt = MethodResult("gt", "GT", None, None, table({**RAW, "fgd": (math.nan,) * 3}), reference=True)
    ours = MethodResult("model", "Ours", True, 312.4, table(RAW))
    random = MethodResult("random", "Random", False, 25.0, table(RAW))
    text = table1_markdown([gt, random, ours], "Table 1: caption")
    lines = text.splitlines()
    assert lines[0] == "**Table 1: caption**"
    header, rule, *rows = lines[2:]
    cells = [c.strip() for c in header.strip("|").split("|")]
    # metrics the rows hold, in registry order; the Fréchet ones add a Pooled column
    assert cells[:4] == ["Method", "C", "R", "FPS"] and len(cells) == 4 + 2 * len(RAW) + 2
    assert cells[4] == "FGD ↓ (×10^1) Avg (95 %)" and cells[7] == "FGD_acc ↓ (×10^5) Avg (95 %)"
    assert cells[6] == cells[9] == "Pooled (95 %)"
    assert cells[10] == "Foot Slide ↓ ∈ [0, 1] Avg (95 %)" and cells[14] == "Head Ang. ↑ ∈ [-1, 1] Avg (95 %)"
    assert all(cells[i] == "NS/S" for i in (5, 8, 11, 13, 15))
    assert rule.count("|") == len(cells) + 1
    parse = lambda line: [c.strip() for c in line.strip("|").split("|")]  # noqa: E731
    gt_cells, random_cells, ours_cells = (parse(r) for r in rows)
    assert gt_cells[:7] == ["GT", "-", "-", "-", "-", "-/-", "-"]  # FGD is not shown for GT
    assert random_cells[1:4] == ["✗", "✗", "25"]  # 25 FPS is not real time at 30 fps
    assert ours_cells[1:4] == ["✓", "✓", "312"]
    assert ours_cells[4:10] == ["1.28", "0.35/0.87", "-", "2.19", "0.01/7.81", "-"]  # raw / 10, / 1e5
    assert ours_cells[10:16] == ["0.01", "0.01/-", "105.0", "90.1/146.2", "0.83", "0.82/0.85"]


def test_table2_markdown_rows_per_gaze():
    rows = [MethodResult(f"model@{g}", "m", True, 300.0, table(RAW), gaze=g) for g in (None, 0.0, 1.0)]
    lines = table2_markdown(rows, "Table 2").splitlines()
    header = [c.strip() for c in lines[2].strip("|").split("|")]
    assert header[0] == "g" and header[1] == "FGD ↓ (×10^1)" and len(header) == 1 + len(RAW)
    assert [line.split("|")[1].strip() for line in lines[4:]] == ["∅", "0.0", "1.0"]
    assert lines[4].split("|")[2].strip() == "1.28"


def test_paired_comparison_cancels_what_the_windows_share():
    """Clips that differ from GT by a constant: the difference's interval is that constant
    exactly, however widely the windows spread, while each mean's own interval is wide; the
    ratio of a scaled copy is its factor; no interval without clips or where GT's mean is 0."""
    from sarah_models.evaluation.metrics.table import bootstrap_interval, paired_comparison

    gt = np.random.default_rng(1).normal(50.0, 20.0, size=300)
    shifted = paired_comparison(gt + 0.04, gt)
    assert shifted["gap"] == pytest.approx(0.04)
    assert shifted["gap_low"] == pytest.approx(0.04) and shifted["gap_high"] == pytest.approx(0.04)
    low, high = bootstrap_interval(gt + 0.04)
    assert high - low > 2.0  # unpaired, the two means' intervals overlap entirely
    scaled = paired_comparison(1.2 * gt, gt)
    assert (scaled["ratio_low"], scaled["ratio"], scaled["ratio_high"]) == pytest.approx((1.2,) * 3)
    noisy = paired_comparison(gt + np.random.default_rng(2).normal(0.0, 1.0, 300), gt)
    assert noisy["gap_low"] < noisy["gap"] < noisy["gap_high"]
    assert paired_comparison([], []) == {}
    assert "ratio" not in paired_comparison([1.0, 2.0], [0.0, 0.0])
    assert "ratio" not in paired_comparison(gt + 0.04, gt, ratio=False)


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    shards = root / "shards"
    # test: 2 sequences x 2 tracked windows of 16 frames x 2 agents = 8 windows
    write_split_shards(shards, {"train": 3, "test": 2}, frames=40)
    return {"shards": shards, "run": save_run(root / "run"), "root": root}


def eval_args(tiny, out, *extra):
    return ["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--out", str(out),
            "--window", str(WINDOW), "--library-size", "8", "--batch-clips", "3",
            "--device", "cpu", "--no-progress", *extra]


def test_end_to_end_tables_plots_and_determinism(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(eval_args(tiny, out, "--windows", "6", "--gaze", "none,0.0,1.0")) == 0
    printed = capsys.readouterr().out
    assert "Table 1" in printed and "Table 2" in printed
    t1 = json.loads((out / "table1.json").read_text())
    assert [r["key"] for r in t1["rows"]] == ["gt", "real", "random", "nn", "model"]
    assert t1["num_windows"] == 6 and t1["available_windows"] == 8
    assert t1["num_speaking"] + t1["num_non_speaking"] == 6
    assert "6 of 8 test windows" in t1["caption"] and f"T = {WINDOW} frames" in t1["caption"]
    assert f"S = speaking ({t1['num_speaking']} seq.)" in t1["caption"]
    gt, real, random, nn, model = t1["rows"]
    assert gt["shown"]["fgd/avg"] is None and gt["fps"] is None
    # The floor row: real clips of other windows, scored like a method, untimed.
    assert real["fps"] is None and real["shown"]["fgd/avg"] > 0
    assert real["shown"]["fgd/pooled"] is None  # all windows pooled: the same set, 0 by design
    assert random["shown"]["fgd/pooled"] > 0
    assert real["shown"]["frame0_offset/avg"] >= 0 and real["shown"]["bone_length/avg"] >= 0
    for row in (real, random, nn, model):
        for name in METRICS:  # every Avg comes with a 95 % interval around it
            low, avg, high = (row["shown"][f"{name}/{k}"] for k in ("low", "avg", "high"))
            assert low <= avg + 1e-9 and avg <= high + 1e-9
    assert gt["shown"]["head_angle/avg"] is not None and -1 <= gt["shown"]["head_angle/avg"] <= 1
    for row in (random, nn, model):
        assert row["fps"] > 0 and row["shown"]["fgd/avg"] > 0
        assert row["raw"]["num_clips"] == 6 and row["raw"]["num_batches"] == 2
        assert row["shown"]["fgd/avg"] == pytest.approx(row["raw"]["values"]["fgd"]["avg"] / 10)
    assert model["causal"] is True and random["causal"] is False and model["gaze"] is None
    t2 = json.loads((out / "table2.json").read_text())
    assert [r["gaze"] for r in t2["rows"]] == [None, 0.0, 1.0]
    assert t2["rows"][0]["shown"] == model["shown"]  # Table 1's model row is the ∅ run
    assert t2["gt_head_angle"] == gt["shown"]["head_angle/avg"]
    md = (out / "table1.md").read_text().splitlines()
    assert [line.split("|")[1].strip() for line in md[4:8]] == ["GT", "Real (other windows)",
                                                                "Random", "NN"]
    assert "Avg (95 %)" in md[2] and "Pooled" in md[2]
    beside = md[md.index("**Beside GT on the same windows: difference (this − GT) and, for "
                         "magnitudes, ratio (this ÷ GT) of the means, paired 95 % bootstrap "
                         "intervals.**"):]
    rows_of = lambda table: [line.split("|")[1].strip()  # noqa: E731
                             for line in table[4:table.index("", 4)]]
    assert rows_of(beside) == [r["method"] for r in (real, random, nn, model)]
    by_part = md[next(i for i, line in enumerate(md) if "by body part" in line):]
    assert rows_of(by_part + [""]) == [r["method"] for r in (real, random, nn, model)]
    whole, *heads = (cell.strip()[:-1].split(" (") for cell in by_part[2].split("|")[2:-1])
    parts = [name for name, _ in heads]
    assert whole[0] == "whole shell" and parts and sum(int(n) for _, n in heads) == int(whole[1])
    for row in (real, random, nn, model):  # FGD_acc of every part, its energy beside GT's
        shown = row["shown"]
        for part in parts:
            avg, low, high, ratio = (shown[f"fgd_acc@{part}/{k}"]
                                     for k in ("avg", "low", "high", "ratio"))
            assert avg >= 0 and low <= avg + 1e-9 <= high + 2e-9 and ratio > 0
    assert all(f"fgd_acc@{part}/avg" not in gt["shown"] for part in parts)  # GT: no distance
    for row in t1["rows"]:  # the JSON gives the rows back as they were shown
        assert MethodResult.from_dict(row).to_dict() == row
    # rows of evaluations of the same windows, in one figure; a row without parts is refused
    figure = tmp_path / "parts.png"
    assert plot_parts_script.main([str(figure), f"{out / 'table1.json'}:random",
                                   f"{out / 'table1.json'}:model=the model"]) == 0
    with Image.open(figure) as png:
        assert png.format == "PNG" and png.size[0] > 200
    capsys.readouterr()
    for bad, problem in ((":gt", "not scored by body part"), (":nobody", "no row 'nobody'"),
                         ("", "want TABLE1_JSON:KEY")):
        assert plot_parts_script.main([str(tmp_path / "bad.png"), f"{out / 'table1.json'}{bad}"]) == 2
        message = capsys.readouterr().err.strip()
        assert problem in message and len(message.splitlines()) == 1
    other = json.loads((out / "table1.json").read_text())  # another window's split of the shell
    split = other["rows"][-1]["raw"]["shell_parts"]
    first, second = list(split)[:2] if len(split) > 1 else (list(split)[0], "elsewhere")
    split.setdefault(second, []).append(split[first].pop())
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert plot_parts_script.main([str(tmp_path / "bad.png"), f"{out / 'table1.json'}:random",
                                   f"{tmp_path / 'other.json'}:model"]) == 2
    assert "split the shell differently" in capsys.readouterr().err
    assert not (tmp_path / "bad.png").exists()
    for row in (real, random, nn, model):  # each per-clip metric paired with GT's, same windows
        shown = row["shown"]
        for name in ("wrist_speed", "head_angle"):
            gap, low, high = (shown[f"{name}/{k}"] for k in ("gap", "gap_low", "gap_high"))
            assert gap == pytest.approx(shown[f"{name}/avg"] - gt["shown"][f"{name}/avg"], abs=1e-9)
            assert low <= gap + 1e-9 <= high + 2e-9
        ratio = shown["wrist_speed/ratio"]
        assert ratio == pytest.approx(shown["wrist_speed/avg"] / gt["shown"]["wrist_speed/avg"])
        assert shown["wrist_speed/ratio_low"] <= ratio <= shown["wrist_speed/ratio_high"]
        assert shown["fgd/gap"] is None  # Fréchet metrics are distances to GT already
        assert shown["head_angle/ratio"] is None  # compared by difference only
    # The Table 1 model row's latents against the encoder's of the same windows.
    latents = json.loads((out / "latents.json").read_text())
    assert latents["windows"] == 6 and latents["tokens"] == WINDOW // 4
    assert sum(band["share"] for band in latents["bands"]) == pytest.approx(1.0)
    assert latents["bands"][0]["directions"][0] == 0
    assert latents["bands"][-1]["directions"][1] == latents["channels"]
    for band in latents["bands"]:
        assert band["spread_low"] <= band["spread"] <= band["spread_high"]
    r2 = latents["per_direction"]["placement_r2"]  # where each direction puts the pelvis
    assert len(r2) == latents["channels"] and all(0 <= v <= 1 + 1e-9 for v in r2)
    steps = latents["steps"]  # the plane that carries each token's floor step
    assert 0 <= steps["r2"] <= 1 and steps["spread_low"] <= steps["spread"] <= steps["spread_high"]
    assert "steps (a plane)" in (out / "latents.md").read_text()
    assert "Latent directions:" in printed and "Latent directions" in (out / "latents.md").read_text()
    listing = json.loads((out / "windows.json").read_text())["windows"]
    assert len(listing) == 6 and {w["start"] for w in listing} <= {0, 16}
    assert sum(w["speaking"] for w in listing) == t1["num_speaking"]
    for name in [f"metric_{m}.png" for m in METRICS] + ["gaze_control.png", "paths.png",
                                                        "fgd_acc_by_part.png",
                                                        "latent_directions.png"]:
        with Image.open(out / "plots" / name) as png:
            assert png.format == "PNG" and png.size[0] > 200
    assert not [p for p in out.rglob(".*")]  # no temporary files left

    # Same inputs, same seed: the same numbers (speed aside).
    again = tmp_path / "again"
    assert main(eval_args(tiny, again, "--windows", "6", "--gaze", "none,0.0,1.0")) == 0
    rows_again = json.loads((again / "table1.json").read_text())["rows"]
    assert [r["shown"] for r in rows_again] == [r["shown"] for r in t1["rows"]]


def test_streaming_protocol_and_subset_of_methods(tiny, tmp_path):
    out = tmp_path / "out"
    assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "0.8", "--table1-gaze",
                          "0.8", "--protocol", "stream", "--windows", "100")) == 0
    t1 = json.loads((out / "table1.json").read_text())
    assert [r["key"] for r in t1["rows"]] == ["gt", "model"] and t1["num_windows"] == 8
    assert "all the split has; 100 requested" in t1["caption"]
    assert t1["rows"][1]["gaze"] == 0.8 and "stream" in t1["rows"][1]["method"]


def test_history_sets_what_a_stream_keeps(tiny, tmp_path):
    """--history: the streamed model row keeps that many latents of history (by default what
    the flow's attention window holds, the paper's 2 for the tiny preset, recorded as the number
    and not named in the caption); another number, or 'all', changes the motion and is named."""
    rows, captions = {}, {}
    for history in ("window", "2", "0", "all"):
        out = tmp_path / history
        assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none",
                              "--protocol", "stream", "--history", history)) == 0
        t1 = json.loads((out / "table1.json").read_text())
        rows[history], captions[history] = t1["rows"][1]["shown"], t1["caption"]
        expected = {"all": None, "window": 2}[history] if history in ("all", "window") else int(history)
        assert t1["settings"]["history_tokens"] == expected
    assert "history" not in captions["2"] and "history" not in captions["window"]
    assert rows["window"] == rows["2"]
    assert "stream protocol (history: 0 tokens)" in captions["0"]
    assert "stream protocol (history: all tokens)" in captions["all"]
    assert rows["0"]["fgd_local/avg"] != rows["2"]["fgd_local/avg"]
    assert rows["all"]["fgd_local/avg"] != rows["0"]["fgd_local/avg"]


def test_trajectory_imputation_streams_what_the_offline_protocol_scores(tiny, tmp_path):
    """--imputation trajectory: the streamed model row is the offline protocol's, figure for
    figure (the caption names it); the paper's imputation streams other figures."""
    rows, captions = {}, {}
    for name, flags in (("offline", ("--protocol", "offline")),
                        ("trajectory", ("--protocol", "stream", "--imputation", "trajectory")),
                        ("final", ("--protocol", "stream"))):
        out = tmp_path / name
        assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none", *flags)) == 0
        t1 = json.loads((out / "table1.json").read_text())
        rows[name], captions[name] = t1["rows"][1]["shown"], t1["caption"]
    assert "stream protocol (trajectory imputation)" in captions["trajectory"]
    assert "imputation" not in captions["final"] + captions["offline"]
    figures = [k for k, v in rows["offline"].items() if isinstance(v, float) and "fps" not in k]
    assert "fgd_local/avg" in figures and "wrist_speed/avg" in figures

    def largest_gap(name: str) -> float:
        return max(abs(rows[name][k] - rows["offline"][k]) / max(abs(rows["offline"][k]), 1e-6)
                   for k in figures)
    assert largest_gap("trajectory") < 1e-5  # float rounding (measured 8e-7)
    assert largest_gap("final") > 1e-3  # these 4-token windows: 0.017 measured


def test_guide_sets_what_the_unconditional_pass_drops(tiny, tmp_path):
    """--guide: guiding gaze alone at g = none is no guidance at all (the same row as w = 1);
    guiding some modalities is a row of its own, named in the caption; the paper's all is not."""
    rows, captions = {}, {}
    for name, flags in (("all", ()), ("gaze", ("--guide", "gaze")), ("w1", ("--cfg", "1")),
                        ("audio", ("--guide", "agent_audio,user_audio"))):
        out = tmp_path / name
        assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none", *flags)) == 0
        t1 = json.loads((out / "table1.json").read_text())
        rows[name], captions[name] = t1["rows"][1]["shown"], t1["caption"]
        # where the windows came from, whatever folder the command ran in
        assert t1["settings"]["shards"] == str(Path(tiny["shards"]).resolve())
    assert rows["gaze"]["fgd_local/avg"] == rows["w1"]["fgd_local/avg"]
    assert rows["audio"]["fgd_local/avg"] not in (rows["all"]["fgd_local/avg"],
                                                  rows["w1"]["fgd_local/avg"])
    assert "guiding agent_audio, user_audio only" in captions["audio"]
    assert "guiding" not in captions["all"]
    with pytest.raises(SystemExit) as exit_:
        main(eval_args(tiny, tmp_path / "bad", "--guide", "user_head,elbows"))
    assert exit_.value.code == 2


def test_noise_scale_reaches_the_model_and_the_caption(tiny, tmp_path):
    """--noise-scale: the model row samples at that temperature, which the caption and the
    settings name; the paper's 1 is not named."""
    rows, captions = {}, {}
    for scale in ("1", "0.5"):
        out = tmp_path / scale
        assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none",
                              "--protocol", "stream", "--noise-scale", scale)) == 0
        t1 = json.loads((out / "table1.json").read_text())
        rows[scale], captions[scale] = t1["rows"][1]["shown"], t1["caption"]
        assert t1["settings"]["noise_scale"] == float(scale)
    assert "noise scale" not in captions["1"] and "noise scale 0.5" in captions["0.5"]
    assert rows["0.5"]["wrist_speed/avg"] != rows["1"]["wrist_speed/avg"]


def test_solver_reaches_the_model_and_the_caption(tiny, tmp_path, capsys):
    """--solver: the model row integrates with that method (Euler at twice the steps makes as
    many network evaluations as the paper's midpoint, and other motion), which the caption and
    the settings name; an unknown solver is refused before any work."""
    rows, captions = {}, {}
    for name, flags in (("midpoint", ()), ("euler", ("--solver", "euler", "--steps", "8"))):
        out = tmp_path / name
        assert main(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none", *flags)) == 0
        t1 = json.loads((out / "table1.json").read_text())
        rows[name], captions[name] = t1["rows"][1]["shown"], t1["caption"]
        assert t1["settings"]["solver"] == name
    assert "4 midpoint steps" in captions["midpoint"] and "8 euler steps" in captions["euler"]
    assert rows["euler"]["fgd_local/avg"] != rows["midpoint"]["fgd_local/avg"]
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(eval_args(tiny, tmp_path / "bad", "--solver", "rk4"))
    assert exit_.value.code == 2 and "invalid choice: 'rk4'" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    with pytest.raises(EvalError, match="unknown solver 'rk4'; choose from midpoint, euler"):
        EvalConfig(solver="rk4")  # the library's callers get the same line


def test_baselines_can_draw_from_another_corpus(tiny, tmp_path, capsys):
    """--library-shards: Random and NN retrieve from a training corpus other than the evaluated
    one (for test fixtures the model never saw); the evaluated windows stay the same."""
    other = tmp_path / "other"
    write_split_shards(other, {"train": 3, "test": 1}, frames=40, seed=5)
    runs = {}
    for name, extra in (("own", ()), ("other", ("--library-shards", str(other)))):
        out = tmp_path / name
        assert main(eval_args(tiny, out, "--methods", "gt,random,nn", *extra)) == 0
        runs[name] = {r["key"]: r for r in json.loads((out / "table1.json").read_text())["rows"]}
    assert runs["own"]["gt"]["shown"] == runs["other"]["gt"]["shown"]
    assert runs["own"]["random"]["shown"]["fgd/avg"] != runs["other"]["random"]["shown"]["fgd/avg"]
    capsys.readouterr()
    assert "nope" in _error(capsys, eval_args(tiny, tmp_path / "x", "--methods", "gt,random",
                                              "--library-shards", str(tmp_path / "nope")))


def test_vae_reconstruction_row_is_opt_in_and_needs_only_the_vae(tiny, tmp_path):
    out = tmp_path / "out"
    assert main(eval_args(tiny, out, "--methods", "gt,model,vae", "--gaze", "none",
                          "--windows", "4")) == 0
    rows = {r["key"]: r for r in json.loads((out / "table1.json").read_text())["rows"]}
    assert list(rows) == ["gt", "model", "vae"] and rows["vae"]["causal"] is True
    assert rows["vae"]["shown"]["fgd/avg"] > 0 and rows["vae"]["fps"] > 0
    assert "VAE (reconstruction)" in (out / "table1.md").read_text()
    parts = json.loads((out / "reconstruction.json").read_text())["parts"]
    assert set(parts) == {"root", "spine and head", "legs", "feet", "arms", "hands", "shell"}
    for part, row in parts.items():
        assert 0 < row["position_low"] <= row["position"] <= row["position_high"]
        assert ("orientation" in row) == (part != "shell")
    assert "| feet |" in (out / "reconstruction.md").read_text()

    vae_only = tmp_path / "vae_run"
    vae_only.mkdir()
    payload = load_checkpoint(tiny["run"] / "flow.pt")
    del payload["flow"]
    save_checkpoint(vae_only / "vae.pt", {**payload, "stage": "vae"})
    again = tmp_path / "again"
    assert main(eval_args(dict(tiny, run=vae_only), again, "--methods", "gt,vae", "--windows",
                          "4")) == 0
    shown = [r["shown"] for r in json.loads((again / "table1.json").read_text())["rows"]]
    assert shown[1] == rows["vae"]["shown"]  # the same VAE from vae.pt as from flow.pt
    (vae_only / "vae.pt").unlink()
    assert main(eval_args(dict(tiny, run=vae_only), again, "--methods", "gt,vae")) == 2


def test_calibration_rows_degrade_the_ground_truth_by_known_amounts(tiny, tmp_path):
    out = tmp_path / "out"
    # no model is needed: the rows are the ground truth's own
    assert main(eval_args(tiny, out, "--methods", "gt,blur,jitter", "--gaze", "none",
                          "--blur-frames", "5", "--jitter-mm", "2")[2:]) == 0
    rows = {r["key"]: r for r in json.loads((out / "table1.json").read_text())["rows"]}
    assert list(rows) == ["gt", "blur", "jitter"]
    blur, jitter = rows["blur"], rows["jitter"]
    assert blur["method"] == "GT, blurred (5 frames)" and jitter["method"] == "GT + 2 mm jitter"
    assert blur["fps"] is None and jitter["fps"] is None and blur["causal"] is None
    # a blur slows the wrists (these shards' motion is a random walk); both rows have
    # accelerations the ground truth has not, and the noise leaves the path where it was
    assert rows["blur"]["shown"]["wrist_speed/avg"] < rows["gt"]["shown"]["wrist_speed/avg"]
    assert jitter["shown"]["fgd/avg"] < 1e-3 * blur["shown"]["fgd/avg"]
    assert blur["shown"]["fgd_acc/avg"] > 0 and jitter["shown"]["fgd_acc/avg"] > 0
    table = (out / "table1.md").read_text()
    assert "GT, blurred (5 frames)" in table and "GT + 2 mm jitter" in table
    # no blur and no noise: the ground truth itself, every distance 0
    same = tmp_path / "same"
    assert main(eval_args(tiny, same, "--methods", "gt,blur,jitter", "--gaze", "none",
                          "--blur-frames", "1", "--jitter-mm", "0")[2:]) == 0
    for row in json.loads((same / "table1.json").read_text())["rows"][1:]:
        assert row["shown"]["fgd_acc/avg"] == pytest.approx(0, abs=1e-6)
        assert row["shown"]["fgd/avg"] == pytest.approx(0, abs=1e-6)


def test_degradations_are_seeded_and_keep_the_path():
    rng = np.random.default_rng(1)
    motion = np.cumsum(rng.normal(0, 0.01, (40, 6)), axis=0).astype(np.float32)
    assert np.array_equal(blurred(motion, 1), motion)
    smooth = blurred(motion, 5)
    assert smooth.shape == motion.shape and smooth.dtype == np.float32
    # a moving average keeps a straight line (away from the ends) and smooths the rest
    line = np.outer(np.arange(40), [0.1, -0.2]).astype(np.float32)
    assert np.allclose(blurred(line, 5)[2:-2], line[2:-2], atol=1e-5)
    assert np.abs(np.diff(smooth, 2, axis=0)).mean() < np.abs(np.diff(motion, 2, axis=0)).mean()
    noisy = jittered(motion, 1.0, seed=3, index=7)
    assert np.array_equal(noisy, jittered(motion, 1.0, seed=3, index=7))
    assert not np.array_equal(noisy, jittered(motion, 1.0, seed=3, index=8))
    assert abs(float((noisy - motion).std()) - 0.001) < 0.0002
    assert np.array_equal(jittered(motion, 0.0), motion)
    with pytest.raises(ValueError, match="frames"):
        blurred(motion, 0)
    with pytest.raises(ValueError, match="mm"):
        jittered(motion, -1.0)


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("sarah-eval: error:")
    return err[-1]


def test_one_line_errors(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    missing = dict(tiny, run=tmp_path / "nope")
    assert "no such run folder or model file" in _error(capsys, eval_args(missing, out))
    assert "no windows of 16 frames" in _error(capsys, eval_args(tiny, out, "--split", "val"))
    hubert = tmp_path / "hubert"
    write_split_shards(hubert, {"train": 1, "test": 1}, features=("hubert-large",))
    assert "mismatched feature extractor" in _error(capsys, eval_args(dict(tiny, shards=hubert), out))
    assert "--run is required" in _error(capsys, eval_args(dict(tiny, run=None), out)[2:])
    assert "unknown method" in _error(capsys, eval_args(tiny, out, "--methods", "gt,mdm"))
    assert "--jitter-mm must be >= 0" in _error(capsys, eval_args(tiny, out, "--jitter-mm", "-1"))
    assert "--blur-frames must be positive" in _error(capsys, eval_args(tiny, out,
                                                                        "--blur-frames", "0"))
    assert "no manifest" in _error(capsys, eval_args(dict(tiny, shards=tmp_path), out))
    assert not out.exists()


def test_decoded_row_is_the_chains_own_floor(tiny, tmp_path):
    """GT through the run's decoding chain: nothing when the chain is off (the paper's config),
    accelerations the ground truth has not when its seam inertia is on."""
    out = tmp_path / "off"
    assert main(eval_args(tiny, out, "--methods", "gt,decoded", "--gaze", "none",
                          "--windows", "4")) == 0
    rows = {r["key"]: r for r in json.loads((out / "table1.json").read_text())["rows"]}
    assert list(rows) == ["gt", "decoded"] and rows["decoded"]["fps"] is None
    assert rows["decoded"]["method"] == "GT, decoded (the run's chain)"
    assert rows["decoded"]["shown"]["fgd_acc/avg"] == pytest.approx(0, abs=1e-6)

    seams = tmp_path / "seams"
    seams.mkdir()
    payload = load_checkpoint(tiny["run"] / "flow.pt")
    payload["config"]["vae"]["boundary_inertia"] = 0.7
    save_checkpoint(seams / "flow.pt", payload)
    on = tmp_path / "on"
    assert main(eval_args(dict(tiny, run=seams), on, "--methods", "gt,decoded", "--gaze", "none",
                          "--windows", "4")) == 0
    decoded = json.loads((on / "table1.json").read_text())["rows"][1]["shown"]
    assert decoded["fgd_acc/avg"] > 0


def test_paths_pick_the_windows_where_the_user_walks_most_and_least_and_record_the_pelvis():
    from sarah_data.skeleton import ROOT, MotionLayout
    from sarah_models.evaluation.paths import floor_path_length, pick_windows, recording

    assert pick_windows([3.0, 0.1, 9.0, 5.0, 0.0, 2.0], each=2) == [2, 3, 4, 1]
    assert pick_windows([1.0, 2.0], each=3) == [1, 0]  # none twice
    assert floor_path_length(np.array([[0, 0], [3, 4], [3, 0]])) == pytest.approx(9.0)
    layout = MotionLayout(shell_points=3)
    rng = np.random.default_rng(0)
    motions = {i: rng.normal(size=(5, layout.width)).astype(np.float32) for i in range(4)}
    produce, paths = recording(lambda item, index: motions[index], [1, 3], layout)
    for i in range(4):
        assert produce(None, i) is motions[i]  # the method's motion passes unchanged
    assert sorted(paths) == [1, 3]
    expected = layout.joint_positions(motions[3].astype(np.float64), [ROOT])[:, 0, [0, 2]]
    np.testing.assert_array_equal(paths[3], expected)
