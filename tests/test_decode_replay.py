"""scripts/decode_replay.py: the recorded frames give sarah-eval's offline model row back through
the chain, a decoding setting changes what is replayed, and bad settings stop before any work."""

import numpy as np
import pytest

from helpers import load_script, write_split_shards
from test_generate import save_run

replay = load_script("decode_replay")
WINDOW = 16


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("replay")
    shards = root / "shards"
    write_split_shards(shards, {"train": 2, "test": 2}, frames=40)
    return {"shards": shards, "run": save_run(root / "run")}


def printed_table(tiny, tmp_path, capsys, flag: str, heading: str) -> tuple[str, list[list[str]]]:
    """Record 3 windows with ``flag`` and return what is printed from ``heading`` on, and the
    rows of its table (the header first), each split into cells."""
    out = tmp_path / "decodes.npz"
    assert replay.main(["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--window",
                        str(WINDOW), "--windows", "3", "--record", str(out), flag]) == 0
    printed = capsys.readouterr().out
    table = printed[printed.index(heading):]
    return table, [line.split(" | ") for line in table.splitlines()
                   if line.startswith("| ") and "---" not in line]


def assert_data_then_decodings(rows: list[list[str]], columns) -> None:
    """A table of ``columns`` with the data's row, then the model's and the VAE's decodings."""
    assert len(rows[0]) == len(columns) + 2
    assert [r[:2] for r in rows[1:]] == [["| ground truth", "-"], ["| model", "the model's"],
                                         ["| vae", "the model's"]]
    assert all(len(r) == len(rows[0]) for r in rows)


def test_records_the_model_row_and_replays_other_decodings(tiny, tmp_path, capsys):
    import torch

    from sarah_models.evaluation.runner import EvalConfig, window_generator
    from sarah_models.evaluation.windows import TestWindows, select_windows
    from sarah_data.dataset import WindowDataset
    from sarah_models.generation.run import load_run

    out = tmp_path / "decodes.npz"
    argv = ["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--window", str(WINDOW),
            "--windows", "3", "--record", str(out), "--try", "vae.boundary_inertia=0.8"]
    assert replay.main(argv) == 0
    printed = capsys.readouterr().out
    rows = [line for line in printed.splitlines() if line.startswith("| model |")]
    assert [r.split(" | ")[1] for r in rows] == ["the model's", "vae.boundary_inertia=0.8"]
    assert rows[0].split(" | ")[2] != rows[1].split(" | ")[2]  # the seams decode otherwise
    with np.load(out, allow_pickle=False) as data:
        recorded = {k: data[k] for k in data.files}
    assert recorded["model_frames"].shape == recorded["gt"].shape == (3, WINDOW, recorded["gt"].shape[-1])
    # the model's own decoding of the recorded frames is sarah-eval's offline model row
    models, _ = load_run(tiny["run"], None, device="cpu")
    dataset = WindowDataset.sliding(tiny["shards"], "test", extractor=models.features, window=WINDOW)
    windows = TestWindows(dataset, select_windows(len(dataset), 3))
    generate = window_generator(models, EvalConfig(protocol="offline", device="cpu"), None)
    assert recorded["user"].shape == (3, WINDOW, 2)
    own = replay.decode(models, recorded["model_frames"], recorded["model_stance"], recorded["user"])
    with torch.inference_mode():
        for i in range(3):
            np.testing.assert_array_equal(own[i], generate(windows[i], i).motion)
    # replayed from the file, the same table
    assert replay.main(["--run", str(tiny["run"]), "--replay", str(out), "--try",
                        "vae.boundary_inertia=0.8"]) == 0
    table = lambda text: text[text.index("| motion |"):]
    assert table(capsys.readouterr().out) == table(printed)
    # the head column is sarah-eval's Head Ang. (the recorded ground truth against itself: 0)
    from sarah_data.skeleton import MotionLayout
    from sarah_models.evaluation.metrics.clips import Clip, DecodedClip
    from sarah_models.evaluation.metrics.head_angle import clip_head_angle
    from sarah_models.evaluation.metrics.spec import MetricsConfig as Config

    layout = MotionLayout.from_width(recorded["gt"].shape[-1])
    for motion, user in zip(recorded["gt"], recorded["user"]):
        ico, shell = layout.split(motion)
        clip = DecodedClip(Clip(ico, shell, user), Config().root_joint, False)
        np.testing.assert_allclose(replay.head_angles(motion[None], user[None], layout),
                                   [clip_head_angle(clip, Config())], atol=1e-12)
    assert "| ground truth | - |" in printed and "| +0.000 |" in printed.split("| ground truth |")[1].splitlines()[0]
    # a hold that turns toward the user replays the recorded users' paths; a recording without
    # them (before the seventy-seventh run) is refused for it, by name
    turning = "vae.root_hold=0.05,vae.root_hold_turn=1"
    assert replay.main(["--run", str(tiny["run"]), "--replay", str(out), "--try", turning]) == 0
    assert f"| model | {turning.replace(',', ', ')} |" in capsys.readouterr().out
    old = tmp_path / "old.npz"
    np.savez(old, **{k: v for k, v in recorded.items() if k != "user"})
    with pytest.raises(SystemExit) as stop:
        replay.main(["--run", str(tiny["run"]), "--replay", str(old), "--try", turning])
    assert "no user paths" in str(stop.value.code)


@pytest.mark.parametrize("argv, words", [
    (["--try", "vae.latent_dim=8"], "only decoding settings"),
    (["--try", "vae.root_hold=-1"], "--try 'vae.root_hold=-1'"),
    (["--try", "vae.root_hold_turn=1"], "set vae.root_hold too"),  # this model holds nothing
    (["--record", "x.npz"], "--record needs --shards"),
    (["--replay", "missing.npz"], "no such file"),
    (["--stages-plot", "no-such-folder/stages.png"], "no such folder"),
    (["--stages-plot", "stages.svg"], "name it .png"),
    (["--gait-plot", "no-such-folder/gait.png"], "no such folder"),
    (["--gait-plot", "gait.svg"], "--gait-plot gait.svg: the figure is a PNG"),
    (["--feet-plot", "no-such-folder/feet.png"], "no such folder"),
    (["--feet-plot", "feet.svg"], "--feet-plot feet.svg: the figure is a PNG"),
    (["--knees-plot", "no-such-folder/knees.png"], "no such folder"),
    (["--knees-plot", "knees.svg"], "--knees-plot knees.svg: the figure is a PNG"),
    (["--try", "vae.foot_gap=-0.1"], "foot_gap (metres) must be >= 0"),
])
def test_bad_arguments_stop_before_any_work(tiny, tmp_path, capsys, argv, words):
    argv = ["--run", str(tiny["run"]), *argv]
    if "--record" not in argv and "--replay" not in argv:
        argv += ["--replay", str(tmp_path / "none.npz")]
    with pytest.raises(SystemExit) as stop:
        replay.main(argv)
    assert stop.value.code == 2 and words in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_the_anatomy_tells_seams_and_time_scales_apart(tiny, tmp_path, capsys):
    """--anatomy: motion whose velocity changes only between latent blocks has all of its
    acceleration on the seams, a slow sway none above the band and about 2 / s of it on the
    seams, millimetre jitter nearly all of it above the band; the table gives the data's row
    in cm/s² and every decoding's against it."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.skeleton import MotionLayout, shell_parts

    dataset = WindowDataset.sliding(tiny["shards"], "test", extractor="logmel", window=WINDOW)
    frame = dataset[0]["motion"].numpy().astype(np.float64)[0]
    layout = MotionLayout.from_width(len(frame))
    parts = shell_parts(*layout.split(frame), layout.joint_names)
    stride, frames, windows = 4, 120, 3
    rng = np.random.default_rng(0)
    still = np.broadcast_to(frame, (windows, frames, len(frame)))

    def moved(path):  # (windows, frames, 3): every point moved along it
        return still + np.tile(path, (1, 1, len(frame) // 3))

    def anatomy(motion):
        return replay.anatomy(motion, replay.shell_accelerations(motion, layout), layout, parts,
                              stride)

    def means(motion):  # each part's (seam share, energy below, energy above), windows' means
        return {part: windows.mean(axis=0) for part, windows in anatomy(motion).items()}

    block_velocity = rng.normal(scale=0.01, size=(windows, frames // stride, 3))
    kinked = moved(np.cumsum(np.repeat(block_velocity, stride, axis=1), axis=1))
    sway = moved(0.05 * np.sin(2 * np.pi * np.arange(frames) / 30)[None, :, None] * [1, 0, 1])
    jitter = still + rng.normal(scale=0.001, size=still.shape)
    for part, (seams, low, high) in means(kinked).items():
        assert seams == pytest.approx(1.0), part
    for part, (seams, low, high) in means(sway).items():
        assert abs(seams - 2 / stride) < 0.05 and high < 0.01 * low, part
    for part, (seams, low, high) in means(jitter).items():
        assert high > 10 * low, part
    truth = anatomy(sway)
    assert replay.anatomy_row("ground truth", "-", truth, truth).count("cm/s²") == len(parts)
    found = anatomy(kinked)
    part = next(iter(parts))
    ratios = [found[part][:, k].mean() / truth[part][:, k].mean() for k in (1, 2)]
    assert (f"| model | x | 1.00 (1.00-1.00) / {ratios[0]:.2f}x (" in
            replay.anatomy_row("model", "x", found, truth))
    assert f" / {ratios[1]:.2f}x (" in replay.anatomy_row("model", "x", found, truth)
    # the command line: the table after the main one, a row per motion and decoding
    out = tmp_path / "decodes.npz"
    assert replay.main(["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--window",
                        str(WINDOW), "--windows", "2", "--record", str(out), "--anatomy",
                        "--try", "vae.boundary_inertia=0.8"]) == 0
    printed = capsys.readouterr().out
    table = printed[printed.index("By body part"):]
    assert [line.split(" | ")[0:2] for line in table.splitlines() if line.startswith("| ") and "---" not in line][1:] == [
        ["| ground truth", "-"], ["| model", "the model's"], ["| vae", "the model's"],
        ["| model", "vae.boundary_inertia=0.8"], ["| vae", "vae.boundary_inertia=0.8"]]
    # ... and before it the parts' FGD_acc, a row per decoding: no floor from 2 windows
    parts_table = printed[printed.index("FGD_acc by body part"):printed.index("By body part")]
    assert "no real floor: it needs 32 windows, the recording has 2" in parts_table
    assert [line.split(" | ")[0] for line in parts_table.splitlines()
            if line.startswith("| ") and "---" not in line][1:] == ["| model", "| vae"] * 2


def test_the_parts_table_reads_each_part_against_the_real_floor():
    """Each part's FGD_acc reads its own points: jitter on the arms' points moves the arms' and
    the shell's figures, not the legs'; the real floor is the data's halves against each other,
    and a row reads each part ÷ the floor's."""
    rng = np.random.default_rng(0)
    parts = {"legs": (0, 1, 2), "arms": (3, 4)}
    real = rng.normal(size=(64, 30, 5, 3))
    same = replay.part_distances(real, real, parts)
    assert list(same) == ["shell", "legs", "arms"]
    assert all(np.allclose(batches, 0.0, atol=1e-9) and len(batches) == 4 for batches in same.values())
    shaken = real.copy()
    shaken[:, :, [3, 4]] += rng.normal(scale=2.0, size=shaken[:, :, [3, 4]].shape)
    found = replay.part_distances(shaken, real, parts)
    assert np.allclose(found["legs"], 0.0, atol=1e-9)
    assert found["arms"].min() > 0 and found["shell"].mean() >= found["arms"].mean() * 0.99
    floor = replay.real_floor(real, parts)
    assert len(floor["shell"]) == 2 and floor["shell"].mean() > 0
    assert np.allclose(floor["legs"], replay.part_distances(real[:32], real[32:], parts)["legs"])
    assert replay.real_floor(real[:31], parts) is None
    line = replay.parts_row("model", "x", found, floor)
    assert line.startswith("| model | x | ")
    assert f", {found['arms'].mean() / floor['arms'].mean():.1f}x |" in line
    assert "x" not in replay.parts_row("real floor", "-", floor, floor).split(" | ", 2)[2]


def test_the_stages_follow_the_chain_filter_by_filter(tiny, tmp_path, capsys):
    """--stages: the decoder's frames first, then the motion after each filter of the chain in
    order, the last of them what the whole chain decodes; the table prints a row per stage of
    every motion and decoding, its last stage's FGD_acc the main table's."""
    from sarah_models.generation.run import load_run
    from sarah_models.sampling.decoding import stream_decoding

    out = tmp_path / "decodes.npz"
    settings = "vae.boundary_inertia=0.8,vae.root_hold=0.05"
    assert replay.main(["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--window",
                        str(WINDOW), "--windows", "3", "--record", str(out)]) == 0
    capsys.readouterr()
    with np.load(out, allow_pickle=False) as data:
        recorded = {k: data[k] for k in data.files}
    models, source = load_run(tiny["run"], None, device="cpu")
    tried = replay.tried_models(models, source, settings.split(","))
    frames, stance, users = (recorded[k] for k in ("model_frames", "model_stance", "user"))
    staged = list(replay.stages(tried, frames, stance, users))
    assert [name for name, _ in staged] == ["decoder", "SeamInertia", "RootHold"]
    assert [type(f).__name__ for f in stream_decoding(tried.vae, tried.normalizer).filters] == \
        [name for name, _ in staged[1:]]
    np.testing.assert_array_equal(staged[0][1], frames)
    np.testing.assert_array_equal(staged[-1][1], replay.decode(tried, frames, stance, users))
    # each filter does its own part: the seam filter changes the frames, the hold moves them on
    assert not np.array_equal(staged[1][1], staged[0][1])
    assert not np.array_equal(staged[2][1], staged[1][1])
    # the command line: a row per stage of each motion and decoding, after the other tables
    assert replay.main(["--run", str(tiny["run"]), "--replay", str(out), "--stages",
                        "--try", settings]) == 0
    printed = capsys.readouterr().out
    table = printed[printed.index("By stage of the decoding chain"):]
    rows = [line.split(" | ") for line in table.splitlines()
            if line.startswith("| ") and "---" not in line][1:]
    assert [r[:3] for r in rows] == [
        [f"| {label}", decoding, stage] for decoding, names in (
            ("the model's", ("decoder", "SeamInertia")),
            (settings.replace(",", ", "), ("decoder", "SeamInertia", "RootHold")))
        for label in ("model", "vae") for stage in names]
    main_rows = [line.split(" | ") for line in printed[:printed.index("By stage")].splitlines()
                 if line.startswith(("| model |", "| vae |"))]
    assert len(main_rows) == 4
    for label, decoding, shown, *_ in main_rows:  # shown: "shell (interval) / legs / feet"
        last = [r for r in rows if r[0] == label and r[1] == decoding][-1]
        assert f"{float(last[3].split()[0]):.0f}" == shown.split()[0]
    # --stages-plot: the same table drawn; its numbers are the table's
    import matplotlib.image

    picture = tmp_path / "stages.png"
    assert replay.main(["--run", str(tiny["run"]), "--replay", str(out), "--stages-plot",
                        str(picture), "--try", settings]) == 0
    again = capsys.readouterr().out
    assert again[again.index("By stage"):].startswith(table.rstrip("\n").split("\n")[0])
    assert f"wrote {picture}" in again and matplotlib.image.imread(picture).ndim == 3
    truth = {part: np.ones((3, 3)) for part in ("legs", "arms")}
    found = {"legs": np.array([[0.5, 2.0, 4.0]] * 3), "arms": np.array([[0.5, 0.5, 0.25]] * 3)}
    series = replay.stage_series([("model", "x", "decoder", np.array([10.0, 12.0]), found),
                                  ("model", "x", "FootLock", np.array([3.0]), truth)], truth)
    group = series[("model", "x")]
    assert group["stages"] == ["decoder", "FootLock"] and group["fgd"][:, 0].tolist() == [11.0, 3.0]
    np.testing.assert_allclose(group["parts"]["legs"][:, :, 0], [[2.0, 4.0], [1.0, 1.0]])
    np.testing.assert_allclose(group["parts"]["arms"][:, :, 0], [[0.5, 0.25], [1.0, 1.0]])
    assert replay.plot_stages(tmp_path / "two.png", series).is_file()


def test_the_legs_table_splits_the_legs_and_what_lies_between(tiny, tmp_path, capsys):
    """--legs: the legs' points split by the leg joint each lies nearest to; legs that each move
    as the data's but in step with each other score nothing alone and all of it between the two;
    a vertical shake of the hips reads in their vertical column; left and right knees moved
    together correlate at 1, moved apart near 0."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.skeleton import MotionLayout, shell_parts

    dataset = WindowDataset.sliding(tiny["shards"], "test", extractor="logmel", window=WINDOW)
    frame = dataset[0]["motion"].numpy().astype(np.float64)[0]
    layout = MotionLayout.from_width(len(frame))
    icosahedra, shell = layout.split(frame)
    centres = icosahedra.mean(axis=-2)
    # the test shards' four shell points put a millimetre from a joint each: the right knee, the
    # left hip, the left ankle and the head, which is no leg's
    placed = shell.copy()
    for p, name in enumerate(("right_knee", "left_hip", "left_ankle", "head")):
        placed[p] = centres[layout.joint(name)] + 0.001
    groups = replay.leg_groups(icosahedra, placed, layout)
    assert groups == {"hips": [1], "left knee and ankle": [2], "right knee and ankle": [0]}
    assert sorted(p for points in groups.values() for p in points) == \
        sorted(shell_parts(icosahedra, placed, layout.joint_names)["legs"])
    # FGD_acc of made-up accelerations: two points a group
    rng = np.random.default_rng(0)
    made = {"hips": [0, 1], "left knee and ankle": [2, 3], "right knee and ankle": [4, 5]}
    real = rng.normal(size=(64, 30, 6, 3))
    assert all(np.allclose(v, 0.0, atol=1e-9) for v in replay.leg_distances(real, real, made).values())
    apart = rng.normal(size=real.shape)
    in_step = apart.copy()
    in_step[:, :, [4, 5]] = in_step[:, :, [2, 3]]
    loose, locked = (replay.leg_distances(a, real, made) for a in (apart, in_step))
    assert list(locked) == list(replay.LEG_COLUMNS)
    assert locked["between the two"].mean() > 10 * max(loose["between the two"].mean(),
                                                       locked["right knee and ankle"].mean())
    shaken = apart.copy()
    shaken[:, :, [0, 1], 1] *= 3.0
    hips = replay.leg_distances(shaken, real, made)
    assert hips["hips vertical"].mean() > 10 * hips["hips horizontal"].mean()
    np.testing.assert_allclose(hips["hips horizontal"], loose["hips horizontal"])
    # the correlation of the left and right joints' accelerations
    frames = 60
    still = np.tile(frame, (2, frames, 1))

    def knees(left, right):  # (2, frames, 3) displacements of each knee's icosahedron
        motion = still.copy()
        for name, path in (("left_knee", left), ("right_knee", right)):
            motion[..., layout.joint_slice(name)] += np.tile(path, 12)
        return motion

    path = rng.normal(scale=0.01, size=(2, frames, 3))
    same = replay.leg_correlations(knees(path, path), layout)
    assert same[0] == pytest.approx(1.0) and same[1] == pytest.approx(1.0)
    assert np.isnan(same[2])  # the ankles stand still
    assert replay.legs_row("x", "-", None, same).endswith(" | 1.00 / 1.00 / - |")
    other = replay.leg_correlations(knees(path, rng.normal(scale=0.01, size=path.shape)), layout)
    assert abs(other[0]) < 0.2 and abs(other[1]) < 0.2
    # the command line: the data's row (no floor from 3 windows), then a row per motion and decoding
    _, rows = printed_table(tiny, tmp_path, capsys, "--legs", "The legs' FGD_acc")
    assert len(rows[0]) == len(replay.LEG_COLUMNS) + 3
    assert [r[:2] for r in rows[1:]] == [["| ground truth", "-"], ["| model", "the model's"],
                                         ["| vae", "the model's"]]
    assert rows[1][2:-1] == ["-"] * len(replay.LEG_COLUMNS)
    assert all(len(r) == len(rows[0]) for r in rows)
    # these shards' shell has no leg points: every FGD_acc column reads "-", the correlations not
    assert all(r[2:-1] == ["-"] * len(replay.LEG_COLUMNS) for r in rows[2:])
    assert all(len(r[-1].split(" / ")) == len(replay.LEG_PAIRS) for r in rows[1:])


def test_the_covariance_table_splits_each_part_into_spread_and_directions(tiny, tmp_path, capsys):
    """--covariance: a part whose accelerations are the data's turned another way (the same
    spread along other axes) scores orientation alone, a part whose accelerations are the data's
    doubled scores spectrum alone, and the other parts nothing; each cell adds up."""
    rng = np.random.default_rng(0)
    parts = {"legs": (0, 1, 2), "arms": (3, 4)}
    real = rng.normal(size=(32, 30, 5, 3)) * np.array([3.0, 1.0, 0.3])
    made = real.copy()
    made[:, :, [0, 1, 2]] = real[:, :, [0, 1, 2]][..., [2, 0, 1]]  # each leg point's axes swapped
    made[:, :, [3, 4]] *= 2.0
    found = replay.covariance_terms(made, real, parts)
    assert list(found) == ["shell", "legs", "arms"]
    legs, arms = found["legs"], found["arms"]
    assert legs.orientation > 100 * max(legs.spectrum, 1e-12) and legs.energy == pytest.approx(1.0, abs=0.05)
    assert arms.spectrum > 100 * max(arms.orientation, 1e-12) and arms.energy == pytest.approx(4.0, rel=0.05)
    same = replay.covariance_terms(real, real, parts)
    assert all(t.total < 1e-9 and t.energy == pytest.approx(1.0) for t in same.values())
    line = replay.covariance_row("model", "x", found)
    assert line.startswith("| model | x | ") and line.count(" | ") == 1 + len(found)
    shell = found["shell"]
    assert f"{shell.total:.1f} = {shell.spectrum:.1f} + {shell.orientation:.1f}" in line
    # the command line: a row per motion and decoding, no floor from 3 windows
    table, rows = printed_table(tiny, tmp_path, capsys, "--covariance", "as spectrum + orientation")
    assert "no real floor: it needs 32 windows, the recording has 3" in table
    assert [r[:2] for r in rows[1:]] == [["| model", "the model's"], ["| vae", "the model's"]]
    assert all(len(r) == len(rows[0]) for r in rows) and all(" = " in r[2] for r in rows[1:])


def test_the_gait_table_tells_a_body_that_steps_from_one_that_creeps(tiny, tmp_path, capsys):
    """--gait: a body moved whole in two moves of 0.4 m reads two moves a window of about that
    length, its feet stepping with it and its pelvis accelerating only while they step; a pelvis
    that creeps under feet that stand reads many short, slow moves, its acceleration all where no
    foot steps."""
    from sarah_data.constants import FPS
    from sarah_data.dataset import WindowDataset
    from sarah_data.fixtures.legs import min_jerk
    from sarah_data.skeleton import MotionLayout

    dataset = WindowDataset.sliding(tiny["shards"], "test", extractor="logmel", window=WINDOW)
    frame = dataset[0]["motion"].numpy().astype(np.float64)[0]
    layout = MotionLayout.from_width(len(frame))
    frames, move = 90, 15
    way = np.zeros(frames)
    way[10:10 + move] = 0.4 * min_jerk(np.linspace(0.0, 1.0, move))
    way[10 + move:] = 0.4
    way[50:50 + move] += 0.4 * min_jerk(np.linspace(0.0, 1.0, move))
    way[50 + move:] = 0.8
    stepping = np.tile(frame, (3, frames, 1)).reshape(3, frames, -1, 3)
    stepping[..., 0] += way[:, None]  # every point along x
    found = replay.gait(stepping.reshape(3, frames, -1), layout)
    assert found["moves"].tolist() == [2, 2, 2]
    assert np.all((found["frames"] > 8) & (found["frames"] < move))
    assert np.allclose(found["metres"], 0.4, atol=0.03)
    assert np.allclose(found["peak"], 1.875 * 0.4 / ((move - 1) / FPS), rtol=0.05)  # min-jerk's peak
    assert np.all(found["both"] > 0.2) and found["still"].sum() < 1e-3 * found["energy"].sum()
    creeping = np.tile(frame, (3, frames, 1))
    pelvis = layout.joint_slice("pelvis")
    drift = np.cumsum(np.random.default_rng(0).normal(scale=0.006, size=(3, frames)), axis=1)
    creeping[:, :, pelvis] += np.tile(drift[..., None] * np.array([1.0, 0.0, 0.0]), 12)  # its 12 points
    crept = replay.gait(creeping, layout)
    assert crept["moves"].mean() > 5 and np.median(crept["metres"]) < 0.05
    assert np.all(crept["both"] == 0.0) and crept["still"].sum() == pytest.approx(crept["energy"].sum())
    line = replay.gait_row("model", "x", found)
    assert line.startswith("| model | x | 2.0 (2.0-2.0) | ") and line.count(" | ") == 1 + len(replay.GAIT_COLUMNS)
    # the command line: the data's row, then a row per motion and decoding
    _, rows = printed_table(tiny, tmp_path, capsys, "--gait", "How the body walks")
    assert_data_then_decodings(rows, replay.GAIT_COLUMNS)
    # --gait-plot: the same table, and the pelvis's speed drawn
    import matplotlib.image

    picture = tmp_path / "gait.png"
    assert replay.main(["--run", str(tiny["run"]), "--replay", str(tmp_path / "decodes.npz"),
                        "--gait-plot", str(picture)]) == 0
    again = capsys.readouterr().out
    assert "How the body walks" in again and f"wrote {picture}" in again
    assert matplotlib.image.imread(picture).ndim == 3
    pelvis = found["paths"][[0, 2]]  # the floor paths --gait-plot draws
    assert found["paths"].shape == (3, frames, 2)
    np.testing.assert_allclose(np.linalg.norm(np.diff(pelvis[0], axis=0), axis=-1).sum(), 0.8, atol=1e-6)
    drawn = tmp_path / "two.png"  # windows 0 and 40 of a recording, drawn from their two paths
    assert replay.plot_gait(drawn, [("ground truth", "-", pelvis), ("model", "x", pelvis)], [0, 40]) == drawn
    assert matplotlib.image.imread(drawn).ndim == 3


def test_the_feet_table_tells_feet_that_cross(tiny, tmp_path, capsys):
    """--feet: a standing body's feet read as wide apart; with its left ankle put 5 cm past the
    right one along the hips' line in half of a window's frames, that window reads half its frames
    crossed, narrow and near, and the gap -5 cm there."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.skeleton import MotionLayout

    dataset = WindowDataset.sliding(tiny["shards"], "test", extractor="logmel", window=WINDOW)
    frame = dataset[0]["motion"].numpy().astype(np.float64)[0]
    layout = MotionLayout.from_width(len(frame))
    motion = np.tile(frame, (2, 10, 1))
    standing = replay.feet_apart(motion, layout)
    assert np.all(standing["gap"] > replay.GAP) and np.all(standing["gap"] < 0.4)
    assert standing["near"].tolist() == standing["narrow"].tolist() == standing["crossed"].tolist() == [0, 0]
    hips, ankles = (layout.joint_positions(frame[None], [f"left_{j}", f"right_{j}"])[0]
                    for j in ("hip", "ankle"))
    across = (hips[0] - hips[1]) * [1, 0, 1]
    across /= np.linalg.norm(across)
    move = (ankles[1] - ankles[0]) * [1, 0, 1] - 0.05 * across
    motion[1, 5:, layout.joint_slice("left_ankle")] += np.tile(move, 12)  # its 12 points
    found = replay.feet_apart(motion, layout)
    for key in ("near", "narrow", "crossed"):
        assert found[key].tolist() == [0.0, 0.5]
    np.testing.assert_allclose(found["gap"][1, 5:], -0.05, atol=1e-9)
    np.testing.assert_array_equal(found["gap"][0], standing["gap"][0])
    # each ankle from under its hip: the moved ankle by its move, the other where it stood
    floor = np.array([1.0, 0.0, 1.0])
    under = [np.linalg.norm((ankles[side] - hips[side]) * floor) for side in (0, 1)]
    np.testing.assert_allclose(standing["under"], np.broadcast_to(under, (2, 10, 2)), atol=1e-9)
    np.testing.assert_allclose(found["under"][1, 5:, 0],
                               np.linalg.norm((ankles[0] + move - hips[0]) * floor), atol=1e-9)
    np.testing.assert_array_equal(found["under"][1, :, 1], standing["under"][1, :, 1])
    np.testing.assert_array_equal(found["under"][1, :5], standing["under"][1, :5])
    # the knees: the frame's own angles; a knee whose ankle moved, the angle to the moved one
    knees = layout.joint_positions(frame[None], ["left_knee", "right_knee"])[0]

    def angle(hip, knee, ankle):
        a, b = hip - knee, ankle - knee
        return np.degrees(np.arccos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b)))

    stood = [angle(hips[side], knees[side], ankles[side]) for side in (0, 1)]
    np.testing.assert_allclose(standing["knee"], np.broadcast_to(stood, (2, 10, 2)), atol=1e-6)
    np.testing.assert_allclose(found["knee"][1, 5:, 0], angle(hips[0], knees[0], ankles[0] + move),
                               atol=1e-6)
    np.testing.assert_array_equal(found["knee"][1, :, 1], standing["knee"][1, :, 1])
    line = replay.feet_row("model", "x", found)
    assert line.startswith("| model | x | 25.00 % (") and line.count(" | ") == 1 + len(replay.FEET_COLUMNS)
    moved = np.linalg.norm((ankles[0] + move - hips[0]) * floor)
    window_medians = [np.median(under), np.median([*[under[0], under[1]] * 5, *[moved, under[1]] * 5])]
    cells = line.split(" | ")
    assert cells[-3].startswith(f"{100 * np.mean(window_medians):.1f} (")
    assert cells[-2] == f"{100 * np.percentile(found['under'], 90):.1f}"
    bent = angle(hips[0], knees[0], ankles[0] + move)
    knee_medians = [np.median(stood), np.median([*stood * 5, *[bent, stood[1]] * 5])]
    assert cells[-1].startswith(f"{np.mean(knee_medians):.1f} (") and cells[-1].endswith(") |")

    # the command line: the data's row, then a row per motion and decoding
    _, rows = printed_table(tiny, tmp_path, capsys, "--feet", "How far apart the feet stand")
    assert_data_then_decodings(rows, replay.FEET_COLUMNS)


def test_the_feet_plot_draws_the_windows_where_the_feet_come_nearest(tiny, tmp_path, capsys):
    """--feet-plot: the windows drawn are those whose lowest gap in any decoding is lowest, and the
    table is printed with the figure."""
    import matplotlib.image

    gaps = [np.array([[0.2, 0.2], [0.1, 0.3], [0.3, 0.3], [0.2, -0.1]]),
            np.array([[0.05, 0.2], [0.3, 0.3], [0.3, 0.3], [0.3, 0.3]])]
    assert replay.nearest_windows(gaps, 3) == [0, 1, 3]
    picture, knees = tmp_path / "feet.png", tmp_path / "knees.png"
    out = tmp_path / "decodes.npz"
    assert replay.main(["--run", str(tiny["run"]), "--shards", str(tiny["shards"]), "--window",
                        str(WINDOW), "--windows", "3", "--record", str(out), "--feet-plot",
                        str(picture), "--knees-plot", str(knees)]) == 0
    printed = capsys.readouterr().out
    assert "How far apart the feet stand" in printed and f"wrote {picture} (windows 0, 1, 2)" in printed
    assert f"wrote {knees} (windows 0, 1, 2)" in printed  # the first, the middle, the last
    assert matplotlib.image.imread(picture).ndim == 3 and matplotlib.image.imread(knees).ndim == 3
