"""scripts/motion_anatomy.py's spectrum: the band energies that the nineteenth run's diagnosis
(docs/results.md) reads."""

import numpy as np
import pytest

from helpers import load_script
from sarah_data.constants import FPS, JOINT_NAMES

anatomy = load_script("motion_anatomy")


def test_a_beat_puts_its_acceleration_in_its_band_and_a_walk_puts_none():
    t = np.arange(400) / FPS
    points = np.zeros((400, 3, 3))
    points[:, 0, 0] = 0.02 * np.sin(2 * np.pi * 4.5 * t)  # a 4.5 Hz beat of 2 cm
    points[:, 1, 2] = 1.2 * t  # a steady walk: no acceleration at all
    energy = anatomy.band_energy(points)
    bands = [i for i, (low, high) in enumerate(anatomy.BANDS) if low <= 4.5 < high]
    assert energy[bands[0]] > 0.98 * energy.sum()
    # the power is the second difference's (Parseval over the one-sided spectrum): a sine's
    # acceleration amplitude is (2 FPS sin(pi f / FPS))^2 x its amplitude
    frames = 398
    expected = (2 * FPS * np.sin(np.pi * 4.5 / FPS)) ** 4 * 0.02 ** 2 / 4 * frames ** 2
    assert abs(energy.sum() / expected - 1) < 0.05
    assert anatomy.band_energy(points[:, 1:]).sum() < 1e-12 * energy.sum()
    # the last band holds the Nyquist frequency
    nyquist = np.zeros((400, 1, 3))
    nyquist[::2, 0, 1] = 0.001
    assert anatomy.band_energy(nyquist)[-1] > 0.99 * anatomy.band_energy(nyquist).sum()


def test_every_joint_belongs_to_one_body_part():
    parts = anatomy.part_joints(JOINT_NAMES)
    members = sorted(j for joints in parts.values() for j in joints)
    assert members == list(range(len(JOINT_NAMES)))
    assert len(parts["hands"]) == 30 and len(parts["legs"]) + len(parts["feet"]) == 8


def test_latent_power_lands_in_its_band_and_steps_measure_token_changes():
    token_rate = FPS / 4
    k = np.arange(100)
    latents = np.zeros((100, 3))
    latents[:, 0] = np.sin(2 * np.pi * 0.75 * k / token_rate)  # a 0.75 Hz wobble
    latents[:, 1] = 5.0  # constant: no power anywhere
    power = anatomy.latent_band_power(latents, token_rate)
    wobble = [i for i, (low, high) in enumerate(anatomy.LATENT_BANDS) if low <= 0.75 < high]
    assert power[wobble[0]] > 0.99 * power.sum()
    # Parseval over the one-sided spectrum: a sine of amplitude 1 over N samples has power N^2 / 4
    assert abs(power.sum() / (100 ** 2 / 4) - 1) < 0.05
    # token-to-token alternation sits at Nyquist, in the last band
    alternating = np.where(k % 2 == 0, 1.0, -1.0)[:, None]
    assert anatomy.latent_band_power(alternating, token_rate)[-1] > 0.99 * 100 ** 2
    ramp = np.outer(k, [0.1, 0.1]).astype(float)
    assert abs(anatomy.latent_step(ramp) - 0.1) < 1e-12


def _body(frames: int, shell_joints, rng) -> tuple[np.ndarray, "anatomy.MotionLayout"]:
    """A motion vector (frames, width): every joint's icosahedron at its own place, and one
    shell point 1 cm from each joint of ``shell_joints`` (by name), all still."""
    joints = len(JOINT_NAMES)
    centres = rng.normal(size=(joints, 3)) * 0.5
    icosahedra = centres[:, None] + rng.normal(size=(joints, 12, 3)) * 0.01
    shell = np.stack([centres[JOINT_NAMES.index(name)] + 0.01 for name in shell_joints])
    frame = np.concatenate([icosahedra.ravel(), shell.ravel()])
    motion = np.repeat(frame[None], frames, axis=0)
    return motion, anatomy.MotionLayout.from_width(motion.shape[1])


def test_a_step_reaches_from_where_the_foot_lifts_to_where_it_lands():
    # left foot: stands, walks 40 cm forward in 5 frames, stands, walks 30 cm sideways in 6;
    # right foot stands throughout (a lifted heel without travel is no step)
    feet = np.zeros((40, 2, 3))
    feet[:, 1, 0] = 0.3
    feet[10:15, 0, 2] = np.linspace(0, 0.4, 6)[1:]
    feet[15:, 0, 2] = 0.4
    feet[25:31, 0, 0] = np.linspace(0, 0.3, 7)[1:]
    feet[31:, 0, 0] = 0.3
    feet[5:8, 1, 1] = 0.05
    reaches = anatomy.step_reaches(feet, anatomy.foot_steps(feet))
    assert np.allclose(reaches, [0.4, 0.3])


def test_the_feet_table_prints_the_median_step(capsys):
    from sarah_data.skeleton import FEET, MotionLayout

    layout = MotionLayout.from_width(55 * 36 + 3 * 256)
    motion = np.zeros((60, layout.width))
    points = motion.reshape(60, -1, 3)  # icosahedra first: a joint is the mean of its 12 points
    for foot, x in zip(FEET, (0.1, -0.1)):
        joint = layout.joint(foot)
        points[:, joint * 12:(joint + 1) * 12, 0] = x
    left = layout.joint(FEET[0])
    points[20:, left * 12:(left + 1) * 12, 2] = 0.4  # one 40 cm step in one frame
    anatomy.feet([(motion, motion)], layout)
    shown = capsys.readouterr().out
    row = next(line for line in shown.splitlines() if line.startswith("| ground truth | 1 |"))
    # from frame 18, the last it stands: still at 19, there from 20 on
    assert row.endswith(" | 0 " + " ".join(["100"] * (anatomy.SWING_FRAMES - 1)) + " |")


def test_gliding_legs_ride_the_pelvis_and_leave_the_rest_as_it_was():
    from sarah_data.frames import rotation_about_y

    frames = 40
    still, layout = _body(frames, ["left_knee", "right_foot", "head", "left_wrist"],
                          np.random.default_rng(2))
    t = np.arange(frames)
    pelvis = layout.joint_positions(still[:1], ["pelvis"])[0, 0]
    shift = np.stack([0.03 * t, 0.0 * t, 0.01 * t], -1)
    # The whole body walks and turns about its pelvis, rigidly: its legs already ride the pelvis.
    walked = (np.einsum("tij,tnj->tni", rotation_about_y(0.02 * t), still.reshape(frames, -1, 3) - pelvis)
              + pelvis + shift[:, None]).reshape(frames, -1)
    np.testing.assert_allclose(anatomy.gliding_legs(walked, layout), walked, atol=1e-12)
    # A foot that steps on its own is carried along instead; a nodding head is left alone.
    stepping = walked.copy()
    icosahedra, shell = layout.split(stepping)
    icosahedra[20:, JOINT_NAMES.index("right_foot")] += [0.0, 0.05, 0.4]
    shell[20:, 1] += [0.0, 0.05, 0.4]
    icosahedra[:, JOINT_NAMES.index("head")] += 0.05 * np.sin(t)[:, None, None]
    shell[:, 2] += 0.05 * np.sin(t)[:, None]
    expected = stepping.copy()
    legs = [JOINT_NAMES.index(f"{side}_{part}") for side in ("left", "right")
            for part in ("knee", "ankle", "foot")]
    layout.split(expected)[0][:, legs] = layout.split(walked)[0][:, legs]
    layout.split(expected)[1][:, :2] = layout.split(walked)[1][:, :2]
    given = stepping.copy()
    np.testing.assert_allclose(anatomy.gliding_legs(stepping, layout), expected, atol=1e-12)
    np.testing.assert_array_equal(stepping, given)  # the input is not written to


def test_sampling_flags_are_checked_before_any_model_loads(capsys, tmp_path):
    # no model file exists at --run: a bad guide modality must be refused first, in one line
    missing = str(tmp_path / "absent.safetensors")
    try:
        anatomy.main(["--run", missing, "--shards", str(tmp_path), "--guide", "user_head,smell"])
    except SystemExit as exit_:
        assert exit_.code == 2
    else:
        raise AssertionError("an unknown modality was accepted")
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--guide" in error and "smell" in error


@pytest.mark.filterwarnings("ignore::sarah_models.evaluation.metrics.frechet.FrechetRidgeWarning")
def test_accelerations_split_along_the_users_bearing_and_roles_part_by_pelvis_speed(capsys):
    frames = 90
    still, layout = _body(frames, ["pelvis", "left_knee", "right_foot"], np.random.default_rng(3))
    t = np.arange(frames) / 30.0
    pelvis = layout.joint_positions(still[:1], ["pelvis"])[0, 0]
    user = np.repeat([[pelvis[0], pelvis[2] + 2.0]], frames, axis=0)  # 2 m ahead along z

    def moved(offsets):  # every point shifted by (frames, 3)
        return (still.reshape(frames, -1, 3) + offsets[:, None]).reshape(frames, -1)

    sway = 0.02 * np.sin(2 * np.pi * 2 * t)
    toward = moved(np.stack([0 * t, 0 * t, sway], -1))  # sways toward and away from the user
    around = moved(np.stack([sway, 0 * t, 0 * t], -1))  # sways across the bearing
    energy = lambda m: np.mean(anatomy.along_bearing(  # noqa: E731
        anatomy.accelerations(layout.split(m)[1][:, :3]), m, user, layout) ** 2, axis=(0, 1))
    radial, tangential = energy(toward), energy(around)
    assert radial[0] > 0 and radial[1] < 1e-20 * radial[0] and radial[2] < 1e-20 * radial[0]
    # across the bearing the bearing itself turns a little with the sway (2 cm at 2 m)
    assert tangential[1] > 0 and tangential[0] < 1e-3 * tangential[1]
    np.testing.assert_allclose(radial[0], tangential[1], rtol=1e-3)

    walker = moved(np.stack([0.45 * t, 0 * t, 0 * t], -1))  # walks 0.45 m/s across
    assert abs(anatomy.mean_floor_speed(walker, layout) - 0.45) < 1e-9
    assert anatomy.mean_floor_speed(toward, layout) < anatomy.WALKER_SPEED
    # a model that moves as the ground truth does: every ratio 1, FGD_acc pooled ~0, per role
    clips = [(m, m, user, m, None, m) for m in (walker + around - still, toward)]
    anatomy.roles(clips, layout)
    shown = capsys.readouterr().out
    assert "1 windows where the ground truth's agent walks" in shown
    rows = [line for line in shown.splitlines() if line.startswith(("| walks |", "| stands |"))]
    assert len(rows) == 8 and [r.split(" | ")[1] for r in rows[:4]] == [
        "ground truth", "model, streamed", "model, offline", "VAE reconstruction"]
    assert rows[0].split(" | ")[2] == "0.45" and rows[4].split(" | ")[2] != "0.45"
    # no ratio where the ground truth has no energy: the stander sways only toward the user
    for row in rows[1:4]:
        assert row.endswith(" | 0 |") and row.count("[1.00 / 1.00 / -]") == 3
    for row in rows[5:]:
        assert row.endswith(" | 0 |") and row.count("[1.00 / - / -]") == 3
