"""scripts/choose_sampling.py: it reads sarah-eval's own output, applies its rule, and refuses to
compare settings evaluated on different windows."""

import dataclasses
import json
from pathlib import Path

import pytest

from helpers import load_script
from sarah_cli.eval import main as evaluate
from test_evaluate import eval_args, tiny  # noqa: F401 (tiny is the module's fixture)

choose_sampling = load_script("choose_sampling")

SETTINGS = (("1", "1.3"), ("0.5", "0.5"))


def _evaluate(tiny, out: Path, noise: str, cfg: str, *extra: str) -> Path:  # noqa: F811
    assert evaluate(eval_args(tiny, out, "--methods", "gt,model", "--gaze", "none", "--protocol",
                              "stream", "--noise-scale", noise, "--cfg", cfg, *extra)) == 0
    return out


@pytest.fixture(scope="module")
def folders(tiny, tmp_path_factory):  # noqa: F811
    root = tmp_path_factory.mktemp("settings")
    return [_evaluate(tiny, root / f"{noise}_{cfg}", noise, cfg) for noise, cfg in SETTINGS]


def test_reads_sarah_eval_output_and_chooses_by_its_rule(folders, tmp_path, capsys):
    settings = [choose_sampling.read_setting(f) for f in folders]
    for setting, folder, (noise, cfg) in zip(settings, folders, SETTINGS):
        shown = json.loads((folder / "table1.json").read_text())["rows"][1]["shown"]
        assert (setting.noise_scale, setting.cfg) == (float(noise), float(cfg))
        assert setting.wrists == (shown["wrist_speed/ratio"], shown["wrist_speed/ratio_low"],
                                  shown["wrist_speed/ratio_high"])
        assert setting.head[0] == shown["head_angle/gap"]
        assert setting.distance == max(abs(shown["wrist_speed/ratio"] - 1) / 0.2,
                                       abs(shown["head_angle/gap"]) / 0.05)
    # The untrained model stretches its bones past item 2's 2 %: nothing is eligible, and the
    # command says so instead of naming a setting.
    assert all(s.bone_length > choose_sampling.BONE_LENGTH_MAX for s in settings)
    flags = tmp_path / "flags.txt"
    assert choose_sampling.main([*map(str, folders), "--flags-to", str(flags)]) == 1
    captured = capsys.readouterr()
    assert "no setting keeps foot slide, bone length and frame-0 offset" in captured.err
    assert captured.out.count("\n| 1, 1.3 |") == 1 and "| 0.5, 0.5 |" in captured.out
    assert not flags.exists()

    # With the bones held (as the rigid skeleton holds a trained model's), the nearest wins,
    # whatever the order; a setting outside item 2's other figures never does.
    held = [dataclasses.replace(s, bone_length=0.0) for s in settings]
    nearest = min(held, key=lambda s: s.distance)
    assert choose_sampling.choose(held) is nearest
    assert choose_sampling.choose(held[::-1]) is nearest
    sliding = dataclasses.replace(nearest, foot_slide_gap=0.02)
    assert choose_sampling.choose([sliding]) is None
    assert choose_sampling.choose([sliding, *[s for s in held if s is not nearest]]) is not sliding


def test_other_windows_and_unreadable_folders_are_refused(tiny, folders, tmp_path,  # noqa: F811
                                                          capsys):
    fewer = _evaluate(tiny, tmp_path / "fewer", *SETTINGS[1], "--windows", "4")
    assert choose_sampling.main([str(folders[0]), str(fewer)]) == 2
    assert "evaluated different windows" in capsys.readouterr().err

    for name, text in (("broken", "{"), ("other", '{"rows": 3}')):  # not JSON; not a table
        (tmp_path / name).mkdir()
        (tmp_path / name / "table1.json").write_text(text)
    bad = [str(tmp_path / name) for name in ("broken", "missing", "other")]
    assert choose_sampling.main(bad) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 4 and str(tmp_path / "broken" / "table1.json") in err[0]
    assert "missing" in err[1]
    assert "not a sarah-eval table1.json" in err[2] and "no setting could be read" in err[3]


def test_guided_modalities_are_part_of_a_setting(tiny, folders, tmp_path):  # noqa: F811
    """A folder evaluated with --guide is a setting of its own: named in the table, and its
    flags carry --guide; a table from before --guide guided every modality."""
    guided = choose_sampling.read_setting(
        _evaluate(tiny, tmp_path / "guided", "1", "1.3", "--guide", "user_head,gaze"))
    paper = choose_sampling.read_setting(folders[0])
    assert (guided.noise_scale, guided.cfg, guided.guide) == (1.0, 1.3, ("user_head", "gaze"))
    assert guided.wrists != paper.wrists
    assert guided.flags == "--noise-scale 1 --cfg 1.3 --guide user_head,gaze"
    assert paper.flags == "--noise-scale 1 --cfg 1.3"
    table = choose_sampling.markdown([paper, guided], chosen=guided)
    assert "| 1, 1.3 |" in table and "| **1, 1.3, guiding user_head+gaze (chosen)** |" in table
    old = tmp_path / "old"
    old.mkdir()
    t1 = json.loads((folders[0] / "table1.json").read_text())
    del t1["settings"]["guide"]
    (old / "table1.json").write_text(json.dumps(t1))
    assert choose_sampling.read_setting(old).guide == choose_sampling.MODALITIES


def test_a_guidance_interval_is_part_of_a_setting(tiny, folders, tmp_path):  # noqa: F811
    """A folder evaluated with --guidance-interval is a setting of its own, and its flags give
    the chosen interval back to sarah-eval; a table from before the interval guided every time."""
    timed = choose_sampling.read_setting(
        _evaluate(tiny, tmp_path / "timed", "1", "1.3", "--guidance-interval", "0,0.5"))
    paper = choose_sampling.read_setting(folders[0])
    assert timed.interval == (0.0, 0.5) and paper.interval == (0.0, 1.0)
    assert timed.wrists != paper.wrists
    assert timed.flags == "--noise-scale 1 --cfg 1.3 --guidance-interval 0,0.5"
    assert "| **1, 1.3, at 0 <= tau < 0.5 (chosen)** |" in choose_sampling.markdown(
        [paper, timed], chosen=timed)
    old = tmp_path / "old"
    old.mkdir()
    t1 = json.loads((folders[0] / "table1.json").read_text())
    del t1["settings"]["guidance_interval"]
    (old / "table1.json").write_text(json.dumps(t1))
    assert choose_sampling.read_setting(old).interval == (0.0, 1.0)
