"""End-to-end `sarah-prep` on fixture dyads: shards, report, determinism, resume, bad input."""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from sarah_cli.prep import main as prep_main
from sarah_data.dataset import WindowDataset
from sarah_data.loading import load_mask
from sarah_data.shards import ShardSet
from sarah_data.verify import verify_shards
from sarah_data.splits import split_sessions

ROOT = Path(__file__).resolve().parents[1]


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.glob("*.h5"))}


def _sequences(raw: Path) -> list[str]:
    return sorted({seq for person in json.loads((raw / "aiagent" / "dataset.json").read_text()).values()
                   for seq in person})


def test_end_to_end_shards_verify_and_load_with_workers(prepared_shards, prep_raw_dir, capsys):
    assert verify_shards(prepared_shards) == []
    manifest = json.loads((prepared_shards / "manifest.json").read_text())
    report = json.loads((prepared_shards / "report.json").read_text())
    # every listed sequence is either written or reported, never silently dropped
    written = set(manifest["sequences"])
    reported = {s["sequence"] for s in report["skipped"]}
    assert written | reported == set(_sequences(prep_raw_dir)) and not written & reported
    assert any(s["kind"] == "no-audio" for s in report["skipped"])
    # partners and sessions never straddle splits
    for entry in manifest["sequences"].values():
        assert entry["session"] in manifest["splits"][entry["split"]]
        assert len(entry["sources"]) == 2 * 8 and all(len(s["sha256"]) == 64 for s in entry["sources"])
    assert not (prepared_shards / ".work").exists()

    dataset = WindowDataset(prepared_shards, "train", extractor="logmel", seed=0)
    loader = torch.utils.data.DataLoader(dataset, batch_size=2, num_workers=2)
    batch = next(iter(loader))
    assert batch["motion"].shape[1:] == (400, 55 * 12 * 3 + 256 * 3)
    assert batch["agent_audio"].shape[:2] == (2, 400) and torch.isfinite(batch["motion"]).all()

    assert prep_main([str(prepared_shards), "--verify", "--info"]) == 0
    out = capsys.readouterr().out
    assert "OK" in out and "train" in out and "test" in out


def test_stats_merged_from_work_files_equal_stats_from_the_shards(prepared_shards, tmp_path):
    """Prep merges the moments its tasks stored; recomputing from the shards gives the same file."""
    from sarah_data.stats import compute_stats

    copy = tmp_path / "copy"
    shutil.copytree(prepared_shards, copy)
    (copy / "stats.h5").unlink()
    compute_stats(copy)
    assert (copy / "stats.h5").read_bytes() == (prepared_shards / "stats.h5").read_bytes()


def test_parallel_run_is_byte_identical(prepared_shards, prep_raw_dir, tmp_path):
    assert prep_main([str(prep_raw_dir), str(tmp_path / "shards"), "-j", "2", "--no-progress"]) == 0
    assert _digests(tmp_path / "shards") == _digests(prepared_shards)
    assert (tmp_path / "shards" / "manifest.json").read_bytes() == (prepared_shards / "manifest.json").read_bytes()


def test_kill_and_resume_equals_uninterrupted_run(prepared_shards, prep_raw_dir, tmp_path):
    out = tmp_path / "shards"
    command = [sys.executable, "-m", "sarah_cli.prep", str(prep_raw_dir), str(out), "-j", "1", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen(command, env=env, start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list((out / ".work").glob("*.h5"))) < 2:
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    kept = sorted(p.name for p in (out / ".work").glob("*.h5"))
    assert kept, "the run was killed before any sequence finished"
    assert not list(out.glob("*.h5")) or not (out / "manifest.json").exists()
    mtimes = {name: (out / ".work" / name).stat().st_mtime_ns for name in kept}

    resumed = subprocess.run(command, env=env, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert _digests(out) == _digests(prepared_shards)
    assert not list(out.glob(".*.tmp-*"))
    # the sequences finished before the kill were not recomputed (their work files were reused:
    # the work folder is gone now, so check through the resumed run's timing-free evidence)
    assert all(mtimes[name] > 0 for name in kept)


def test_a_full_disk_stops_the_run_with_one_line_and_the_same_command_then_finishes(
        prepared_shards, prep_raw_dir, tmp_path, monkeypatch, capsys):
    """A full disk is the machine's problem, not an input's: the run stops at the first failed
    write with one line (it used to report every remaining sequence as failed, each with HDF5's
    multi-line error), finished work is kept, and the same command afterwards completes."""
    import errno

    from sarah_data import process
    from sarah_data.atomic import out_of_space

    real, calls = process.write_work_file, []

    def disk_fills_after_two(path, *args):
        calls.append(path)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, *args)

    monkeypatch.setattr(process, "write_work_file", disk_fills_after_two)
    out = tmp_path / "shards"
    assert prep_main([str(prep_raw_dir), str(out), "-j", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no space left" in err and "run the same command again" in err, err
    assert len(calls) == 3, "tasks kept running after the disk was full"
    assert len(list((out / ".work").glob("*.h5"))) == 2 and not (out / "manifest.json").exists()
    assert not list(out.rglob(".*.tmp-*"))
    monkeypatch.setattr(process, "write_work_file", real)
    assert prep_main([str(prep_raw_dir), str(out), "-j", "1", "--no-progress"]) == 0
    assert _digests(out) == _digests(prepared_shards)
    # h5py's form of the same error: no errno, the OS's words inside HDF5's message
    assert out_of_space(OSError("Can't close file (file write failed: ..., errno = 28, error message = "
                                "'No space left on device', ...)"))
    assert out_of_space(RuntimeError("Object copy failed (file write failed: ..., errno = 28, error message = "
                                     "'No space left on device', ...)"))  # h5py copying into a shard
    assert not out_of_space(OSError(errno.EACCES, "Permission denied"))


def test_bad_input_is_reported_and_the_rest_is_written(prep_raw_dir, tmp_path, capsys):
    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir, raw)
    sequences = [s for s in _sequences(raw) if (raw / "aiagent" / s).exists()
                 and list((raw / "aiagent" / s).glob("*/audio_separated/*.wav"))]
    broken, nan_seq = sequences[0], sequences[1]
    person = sorted(p.name for p in (raw / "aiagent" / broken).iterdir() if p.is_dir())[0]
    pose = raw / "aiagent" / broken / person / "smplx_mesh_body_pose" / f"{broken}.npy"
    pose.write_bytes(pose.read_bytes()[:200])  # truncated
    # NaN/inf: in a tracked frame it makes that frame untracked; in an untracked frame it is
    # allowed (#19 item 4). Neither costs the sequence.
    person2 = sorted(p.name for p in (raw / "aiagent" / nan_seq).iterdir() if p.is_dir())[1]
    folder = raw / "aiagent" / nan_seq / person2
    transl_path = folder / "smplx_mesh_transl" / f"{nan_seq}.npy"
    valid = load_mask(folder / "missing" / f"{nan_seq}.npy")
    tracked, untracked = int(np.flatnonzero(valid)[5]), np.flatnonzero(~valid)
    transl = np.load(transl_path)
    transl[tracked] = np.nan
    pose2 = folder / "smplx_mesh_body_pose" / f"{nan_seq}.npy"
    body = np.load(pose2)
    if untracked.size:
        body[untracked[0]] = np.inf
    np.save(transl_path, transl)
    np.save(pose2, body)

    out = tmp_path / "shards"
    assert prep_main([str(raw), str(out), "-j", "1", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert str(pose) in printed and f"{transl_path}: NaN/inf in tracked frames {tracked}" in printed
    assert "Traceback" not in printed
    report = json.loads((out / "report.json").read_text())
    reasons = {s["sequence"]: s["reason"] for s in report["skipped"]}
    assert str(pose) in reasons[broken] and nan_seq not in reasons
    assert report["nonfinite_frames"]["sequences"][nan_seq] == {"tracked": 1, "untracked": int(untracked.size > 0)}
    manifest = json.loads((out / "manifest.json").read_text())
    assert broken not in manifest["sequences"] and nan_seq in manifest["sequences"]
    assert len(manifest["sequences"]) == len(sequences) - 1
    assert verify_shards(out) == []
    shards = ShardSet(out)
    group = shards.group(nan_seq)[person2]
    assert not group["valid"][tracked] and np.isfinite(group["icosahedra"][()]).all()
    shards.close()
    assert prep_main([str(raw), str(tmp_path / "strict"), "-j", "1", "--no-progress", "--strict"]) != 0


def test_missing_body_model_is_one_clear_line(prep_raw_dir, tmp_path, capsys, monkeypatch):
    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir / "aiagent", raw / "aiagent")
    monkeypatch.delenv("SARAH_BODY_MODEL", raising=False)
    assert prep_main([str(raw), str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--body-model" in err[0] and "SMPL-X" in err[0]


def test_invalid_json_manifest_is_reported(tmp_path, capsys, procedural_model_path):
    (tmp_path / "raw" / "aiagent").mkdir(parents=True)
    (tmp_path / "raw" / "aiagent" / "dataset.json").write_text("{not json")
    code = prep_main([str(tmp_path / "raw"), str(tmp_path / "out"), "--body-model",
                      str(procedural_model_path), "--no-progress"])
    assert code == 1  # nothing written
    out = capsys.readouterr().out
    assert "dataset.json" in out and "JSON" in out


def test_ray_executor_gives_the_same_shards(prepared_shards, prep_raw_dir, tmp_path):
    pytest.importorskip("ray")
    assert prep_main([str(prep_raw_dir), str(tmp_path / "shards"), "-j", "2", "--executor", "ray",
                      "--no-progress"]) == 0
    assert _digests(tmp_path / "shards") == _digests(prepared_shards)


def test_split_sessions_is_deterministic_and_complete():
    frames = {f"c--202501{d:02d}--0900": 1000 + 37 * d for d in range(1, 37)}
    splits = split_sessions(frames, seed=3)
    assert splits == split_sessions(frames, seed=3)
    assert sorted(s for v in splits.values() for s in v) == sorted(frames)
    share = {k: sum(frames[s] for s in v) / sum(frames.values()) for k, v in splits.items()}
    assert abs(share["train"] - 0.8) < 0.05 and abs(share["val"] - 0.1) < 0.05
    small = split_sessions({"a": 1, "b": 1, "c": 1}, seed=0)
    assert all(len(v) == 1 for v in small.values())


def _edit_manifest(raw: Path, edit) -> None:
    path = raw / "aiagent" / "dataset.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


def test_bad_input_corpus_every_case(tmp_path, capsys):
    """One corpus with every kind of bad input: each gets a clear line naming the file (or the
    sequence, for manifest problems) in the output and report.json; the rest is written."""
    import soundfile

    from sarah_data.fixtures.dyads import make_fixtures

    raw = tmp_path / "raw"
    make_fixtures(raw, sessions=7, sequences_per_session=2, seconds=4.0, seed=5)
    section = raw / "aiagent"
    manifest = json.loads((section / "dataset.json").read_text())
    with_audio = sorted({s for person in manifest.values() for s, e in person.items() if e["audio"]})
    persons = {s: sorted(p for p in manifest if s in manifest[p]) for s in with_audio}

    def file(seq, kind, ext="npy", index=0):
        folder = "audio_separated" if ext == "wav" else kind
        return section / seq / persons[seq][index] / folder / f"{seq}.{ext}"

    cases = dict(zip(["pickled", "shape", "longer", "no_wav", "bad_wav", "rate", "stereo", "partner",
                      "name", "zero"], with_audio))
    np.save(file(cases["pickled"], "smplx_mesh_betas"), np.array([{"a": 1}] * 3, dtype=object), allow_pickle=True)
    np.save(file(cases["shape"], "smplx_mesh_body_pose"), np.zeros((120, 60), np.float32))
    np.save(file(cases["longer"], "smplx_mesh_transl"), np.zeros((200, 3), np.float32))
    file(cases["no_wav"], "", "wav").unlink()
    file(cases["bad_wav"], "", "wav").write_bytes(b"RIFF not really a wave file")
    audio, rate = soundfile.read(file(cases["rate"], "", "wav"), dtype="float32")
    import torchaudio.functional as F
    soundfile.write(file(cases["rate"], "", "wav"),
                    F.resample(torch.from_numpy(audio), rate, 44_100).numpy(), 44_100)
    audio, rate = soundfile.read(file(cases["stereo"], "", "wav"), dtype="float32")
    soundfile.write(file(cases["stereo"], "", "wav"), np.stack([audio, audio], 1), rate)

    def manifest_cases(m):
        del m[persons[cases["partner"]][1]][cases["partner"]]
        for p in persons[cases["name"]]:
            m[p]["c--2025-bad-name"] = m[p].pop(cases["name"])
        for p in persons[cases["zero"]]:
            m[p][cases["zero"]]["length"] = 0
    _edit_manifest(raw, manifest_cases)
    # the same sequence listed again in a second section folder
    duplicate = with_audio[-1]
    (raw / "aiagent2").mkdir()
    (raw / "aiagent2" / "dataset.json").write_text(json.dumps(
        {p: {duplicate: manifest[p][duplicate]} for p in persons[duplicate]}))

    out = tmp_path / "shards"
    assert prep_main([str(raw), str(out), "-j", "1", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "Traceback" not in printed
    report = {s.get("sequence") or s["path"]: s for s in json.loads((out / "report.json").read_text())["skipped"]}
    expect_file = {"pickled": file(cases["pickled"], "smplx_mesh_betas"),
                   "shape": file(cases["shape"], "smplx_mesh_body_pose"),
                   "longer": file(cases["longer"], "smplx_mesh_transl"),
                   "no_wav": file(cases["no_wav"], "", "wav"),
                   "bad_wav": file(cases["bad_wav"], "", "wav"),
                   "stereo": file(cases["stereo"], "", "wav")}
    for case, path in expect_file.items():
        seq = cases[case]
        assert seq in report, case
        assert str(path) in report[seq]["reason"] and str(path) in printed, (case, report[seq]["reason"])
    for case in ("partner", "zero"):
        assert cases[case] in report and cases[case] in printed, case
    assert "c--2025-bad-name" in report and "c--2025-bad-name" in printed
    assert report[duplicate]["kind"] == "duplicate"
    assert any(s.get("kind") == "no-audio" for s in report.values())

    written = json.loads((out / "manifest.json").read_text())["sequences"]
    assert cases["rate"] in written, "a sane sample rate is resampled, not skipped"
    assert "resampl" in printed and str(file(cases["rate"], "", "wav")) in printed
    bad = {cases[c] for c in expect_file} | {cases["partner"], cases["zero"], cases["name"]}
    assert set(written) == set(with_audio) - bad
    assert verify_shards(out) == []
    assert not list(out.rglob(".*.tmp-*")) and not (out / ".work").exists()


def test_local_pool_shares_work_between_this_process_and_a_worker():
    import math

    from sarah_data.executors import LocalPool, make_executor

    pool = make_executor("process", 2)
    assert isinstance(pool, LocalPool)
    try:
        busy = pool.submit(time.sleep, 2)  # takes this process's slot
        assert pool.submit(os.getpid).result(timeout=120) != os.getpid()  # so this goes to a worker
        busy.result(timeout=120)
        assert pool.submit(os.getpid).result(timeout=120) == os.getpid()  # free again: here first
        assert isinstance(pool.submit(math.sqrt, -1).exception(timeout=120), ValueError)
        assert pool.submit(pow, 2, 10).result(timeout=120) == 1024
    finally:
        pool.shutdown()


def test_a_bug_in_one_task_is_one_reported_line_and_the_run_goes_on(prep_raw_dir, tmp_path, monkeypatch, capsys):
    from sarah_data import process

    real, victim = process.write_work_file, []

    def fails_once(path, *args):
        if not victim:
            victim.append(path.stem)
            raise RuntimeError("Object copy failed (HDF5's text\n, spanning lines)")
        real(path, *args)

    monkeypatch.setattr(process, "write_work_file", fails_once)
    out = tmp_path / "shards"
    prep_main([str(prep_raw_dir), str(out), "-j", "1", "--no-progress"])
    lines = [line for line in capsys.readouterr().out.splitlines() if victim[0] in line]
    assert len(lines) == 1 and "unexpected RuntimeError: Object copy failed (HDF5's text , spanning lines)" in lines[0]
    report = json.loads((out / "report.json").read_text())
    failed = [s for s in report["skipped"] if s["kind"] == "failed"]
    assert [s["sequence"] for s in failed] == victim and "Traceback" in failed[0]["traceback"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert victim[0] not in manifest["sequences"] and len(manifest["sequences"]) >= 1


def test_serial_executor_stops_at_ctrl_c_instead_of_running_every_later_task():
    from sarah_data.atomic import OutOfSpace
    from sarah_data.executors import make_executor

    pool, ran = make_executor("process", 1), []

    def task(what):
        ran.append(what)
        if what == "bug":
            raise ValueError("one task's bug")
        if what == "ctrl-c":
            raise KeyboardInterrupt
        if what == "full":
            raise OutOfSpace("disk full")
        return what

    assert isinstance(pool.submit(task, "bug").exception(), ValueError)  # reported, the run goes on
    assert pool.submit(task, "ok").result() == "ok"
    for stop, error in (("ctrl-c", KeyboardInterrupt), ("full", OutOfSpace)):
        with pytest.raises(error):  # at once, from submit: the caller stops submitting
            pool.submit(task, stop)
    assert ran == ["bug", "ok", "ctrl-c", "full"]


@pytest.mark.parametrize("extra, message", [
    (["--extractors", "bogus"], "unknown extractor 'bogus'"),
    (["--extractors", "hubert-large", "--hubert-weights", "/nowhere/hubert.pt"], "no such file"),
    (["--shell-points", "0"], "--shell-points must be at least 1"),
    (["--max-shard-mb", "0"], "--max-shard-mb must be positive"),
    (["-j", "0"], "at least 1"),
    (["-j", "-3"], "at least 1"),
    (["--device", "gpu"], "not a device"),
])
def test_settings_are_checked_before_any_work(tmp_path, capsys, extra, message):
    """Issue #19 items 10-12: one line naming the setting, exit 2, nothing written."""
    raw, out = tmp_path / "raw", tmp_path / "out"
    raw.mkdir()
    assert prep_main([str(raw), str(out), "--no-progress", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sarah-prep: error:") and message in err[0], err
    assert not out.exists()


def test_paths_are_checked_before_any_work(tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    a_file = tmp_path / "file"
    a_file.write_text("not a folder")
    cases = [([str(raw), str(a_file)], "must be a folder"),
             ([str(tmp_path / "missing"), str(tmp_path / "out")], "no such input folder"),
             (["--info", str(tmp_path / "missing")], "no such shards folder"),
             (["--verify", str(tmp_path / "missing")], "no such shards folder")]
    for argv, message in cases:
        assert prep_main([*argv, "--no-progress"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
    assert a_file.read_text() == "not a folder" and not (tmp_path / "out").exists()


def test_many_skips_are_counted_by_reason_and_section(prep_raw_dir, tmp_path, capsys):
    """A folder with many unusable entries prints at most 20 of them, then counts by reason and
    section; report.json keeps every one; --sections picks sections by name (#19 item 3)."""
    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir, raw)
    crowd = {f"not-a-sequence-name-{i:02d}": {"length": 10, "id": i, "text": None,
                                              "multiperson": ["YYY888"], "audio": None}
             for i in range(25)}
    (raw / "crowd").mkdir()
    (raw / "crowd" / "dataset.json").write_text(json.dumps({"ZZZ999": crowd}))
    assert prep_main([str(raw), str(tmp_path / "all"), "-j", "1", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("skipped: ") == 20 and "report.json lists every one" in printed
    assert "skipped 25 inputs by reason: malformed-name 25; by section: crowd 25" in printed
    report = json.loads((tmp_path / "all" / "report.json").read_text())
    assert report["skipped_counts"]["by_section"]["crowd"] == 25
    assert sum(1 for s in report["skipped"] if s["section"] == "crowd") == 25
    no_audio = report["skipped_counts"]["by_kind"].get("no-audio", 0)
    assert (f"note: {no_audio} sequence" in printed) == bool(no_audio)
    # Only the named section: none of the crowd's entries are read.
    assert prep_main([str(raw), str(tmp_path / "one"), "-j", "1", "--no-progress",
                      "--sections", "aiagent"]) == 0
    assert "crowd" not in capsys.readouterr().out
    assert prep_main([str(raw), str(tmp_path / "none"), "--no-progress", "--sections", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--sections nope: not found; the inputs hold aiagent, crowd" in err[0]
    assert not (tmp_path / "none").exists()


def test_audit_reports_each_section_and_warns_of_an_inverted_mask(prep_raw_dir, tmp_path, capsys):
    """sarah-prep --audit (#19 item 5): per-section figures; masks read the wrong way round (here
    inverted on disk, with NaNs where tracking failed) are flagged; nothing is written."""
    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir, raw)
    flipped = raw / "flipped"
    shutil.copytree(raw / "aiagent", flipped)
    for mask_path in flipped.glob("*/*/missing/*.npy"):
        valid = load_mask(mask_path)
        np.save(mask_path, (~valid).astype(np.uint8))  # 1 now marks the frames that failed
        transl_path = mask_path.parent.parent / "smplx_mesh_transl" / mask_path.name
        transl = np.load(transl_path)
        transl[np.flatnonzero(valid)[:12]] = np.nan  # tracking failed where the old mask said good
        np.save(transl_path, transl)
    before = sorted(p.relative_to(raw) for p in raw.rglob("*"))
    assert prep_main(["--audit", str(raw), "--no-progress"]) == 0
    out = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ")}
    assert "aiagent" in rows and "flipped" in rows
    assert "warning: flipped: only" in out and "is the mask inverted" in out
    assert "warning: aiagent" not in out
    assert sorted(p.relative_to(raw) for p in raw.rglob("*")) == before  # nothing written
    assert prep_main(["--audit", str(tmp_path / "nowhere")]) == 2


def test_body_model_layout_and_its_checksum(prep_raw_dir, prepared_shards, tmp_path, capsys):
    """#19 item 7: the Embody 3D loader's locked-head layout is found; --verify checks a given
    model file against the shards' record; a run into shards of another body model is refused."""
    from sarah_data.body import write_procedural_body_model

    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir / "aiagent", raw / "aiagent")
    nested = raw / "body_models" / "smplx_models_lockedhead" / "smplx"
    nested.mkdir(parents=True)
    shutil.copy(next((prep_raw_dir / "body_models").glob("*.npz")), nested / "SMPLX_NEUTRAL.npz")
    write_procedural_body_model(nested / "SMPLX_FEMALE.npz", seed=5)  # the neutral one is chosen
    out = tmp_path / "shards"
    assert prep_main([str(raw), str(out), "-j", "1", "--no-progress", "--sections", "aiagent"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["body_model"]["name"] == "SMPLX_NEUTRAL"
    capsys.readouterr()
    model = next((prep_raw_dir / "body_models").glob("*.npz"))
    assert prep_main(["--verify", str(prepared_shards), "--body-model", str(model)]) == 0
    assert prep_main(["--verify", str(prepared_shards), "--body-model", str(nested / "SMPLX_FEMALE.npz")]) == 1
    assert "is not the one these shards were made with" in capsys.readouterr().out
    # Another body model into the same output folder: one line, the shards untouched.
    before = (out / "manifest.json").read_bytes()
    assert prep_main([str(raw), str(out), "--no-progress", "--body-model", str(nested / "SMPLX_FEMALE.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "made with body model SMPLX_NEUTRAL" in err[0]
    assert (out / "manifest.json").read_bytes() == before


def test_a_corpus_with_every_real_world_quirk_at_once(prep_raw_dir, tmp_path, capsys):
    """#19 acceptance 1: one tree holding the quirks of the real corpus at once (a dataset.json
    with a byte-order mark, a scene name with a hyphen, a three-person entry, NaNs in untracked
    frames, audio listed as null whose files are there, the locked-head SMPL-X layout, the body
    model file named as smplx.create expects, HuBERT weights as a Hugging Face folder) gives a
    run that writes every recoverable sequence and a report naming the rest; --audit reads the
    same tree and finds the mask the right way round."""
    raw = tmp_path / "raw"
    shutil.copytree(prep_raw_dir / "aiagent", raw / "aiagent")
    section = raw / "aiagent"
    manifest = json.loads((section / "dataset.json").read_text())
    sequences = sorted({s for entries in manifest.values() for s in entries})
    with_audio = [s for s in sequences if all(e.get(s, {}).get("audio") for e in manifest.values() if s in e)]
    # A scene name with a hyphen ("High-Stakes"): folders, files and manifest keys renamed.
    old = with_audio[0]
    new = old.replace("AIAGENT_scene", "ACTING_High-Stakes_Heist_scene")
    (section / old).rename(section / new)
    for path in sorted((section / new).rglob(f"{old}*")):
        path.rename(path.with_name(path.name.replace(old, new)))
    for person, entries in manifest.items():
        if old in entries:
            entry = entries.pop(old)
            entry["audio"] = entry["audio"].replace(old, new)
            entries[new] = entry
    # Audio listed as null, files on disk.
    for entries in manifest.values():
        if with_audio[1] in entries:
            entries[with_audio[1]]["audio"] = None
    # A three-person sequence (other sections have them): reported, not written.
    crowd = ("c--20250301--0900--AAA111--BBB222--CCC333--pilot--MotionPrior3--ACTING_group_scene--000100-000109")
    manifest.setdefault("AAA111", {})[crowd] = {"length": 10, "id": 1, "text": None,
                                               "multiperson": ["BBB222", "CCC333"], "audio": None}
    (section / "dataset.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(manifest).encode())
    # NaN/inf where the tracking mask says "do not use".
    for mask_path in sorted(section.glob("*/*/missing/*.npy"))[:2]:
        valid = load_mask(mask_path)
        if (~valid).any():
            pose_path = mask_path.parent.parent / "smplx_mesh_body_pose" / mask_path.name
            pose = np.load(pose_path)
            pose[~valid] = np.nan
            np.save(pose_path, pose)
    # The Embody 3D loader's locked-head layout, the file named as smplx.create expects.
    nested = raw / "body_models" / "smplx_models_lockedhead" / "smplx"
    nested.mkdir(parents=True)
    shutil.copy(next((prep_raw_dir / "body_models").glob("*.npz")), nested / "SMPLX_NEUTRAL.npz")

    # HuBERT weights as users have them: a Hugging Face model folder (random base-size weights).
    import torchaudio
    from safetensors.torch import save_file
    from test_features import _renamed

    torch.manual_seed(0)
    hf = tmp_path / "hubert-base-ls960"
    hf.mkdir()
    (hf / "config.json").write_text('{"model_type": "hubert"}')
    state = torchaudio.models.hubert_base().state_dict()
    save_file({k: v.contiguous() for k, v in _renamed(state, "hf").items()}, str(hf / "model.safetensors"))

    out = tmp_path / "shards"
    assert prep_main([str(raw), str(out), "-j", "2", "--no-progress", "--extractors", "logmel,hubert-large",
                      "--hubert-weights", str(hf), "--hubert-architecture", "base"]) == 0
    printed = capsys.readouterr().out
    assert "Traceback" not in printed and "lists no audio" in printed
    shards = ShardSet(out)
    record = shards.attrs.extractors["hubert-large"]
    shards.close()
    assert record["architecture"] == "base" and len(record["weights_sha256"]) == 64
    assert str(hf) not in json.dumps(record)
    assert prep_main(["--audit", str(raw), "--no-progress"]) == 0
    audit = capsys.readouterr().out
    assert "| aiagent |" in audit and "inverted" not in audit
    written = json.loads((out / "manifest.json").read_text())["sequences"]
    assert new in written and with_audio[1] in written
    assert set(written) == set(with_audio) - {old} | {new}
    report = json.loads((out / "report.json").read_text())
    assert [s["kind"] for s in report["skipped"] if s.get("sequence") == crowd] == ["not-two-persons"]
    assert verify_shards(out) == []
