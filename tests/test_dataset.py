import hashlib
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st
from scipy.spatial.transform import Rotation

from sarah_data import icosahedron
from sarah_data.constants import JOINT_NAMES
from sarah_data.dataset import (WindowDataset, collate_windows, homogeneous_points,
                                normalize_window, sliding_starts, tracked_runs, valid_starts,
                                window_motion)
from sarah_data.frames import WindowTransform, window_transform
from sarah_data.shards import (MANIFEST_NAME, STATS_NAME, Manifest, ProcessedPerson,
                               ProcessedSequence, ShardError, ShardWriter, write_manifest)
from sarah_data.stats import compute_stats, load_stats
from helpers import shard_attrs

J, V, D = 3, 4, 5
W = 100  # short windows keep the fixtures small; the default (400) is exercised once


def make_person(rng, name, frames, invalid=(), audio=True) -> ProcessedPerson:
    """A walking, turning body: pelvis (joint 0) yaw and tilt vary, other joints around it."""
    yaw = rng.uniform(-np.pi, np.pi) + np.cumsum(rng.normal(0, 0.05, frames))
    tilt = rng.normal(0, 0.1, frames)
    root_rotation = Rotation.from_euler("YX", np.stack([yaw, tilt], 1)).as_matrix()
    root_position = np.stack([np.cumsum(rng.normal(0, 0.01, frames)) + rng.uniform(-2, 2),
                              0.9 + rng.normal(0, 0.01, frames),
                              np.cumsum(rng.normal(0, 0.01, frames)) + rng.uniform(-2, 2)], 1)
    rotations = np.concatenate([root_rotation[:, None],
                                Rotation.random(frames * (J - 1), random_state=rng.integers(1 << 31))
                                .as_matrix().reshape(frames, J - 1, 3, 3)], 1)
    positions = root_position[:, None] + np.concatenate(
        [np.zeros((frames, 1, 3)), rng.normal(0, 0.3, (frames, J - 1, 3))], 1)
    valid = np.ones(frames, bool)
    for a, b in invalid:
        valid[a:b] = False
    return ProcessedPerson(
        name=name,
        icosahedra=icosahedron.encode(positions, rotations).astype(np.float32),
        shell=(root_position[:, None] + rng.normal(0, 0.3, (frames, V, 3))).astype(np.float32),
        head=(root_position[:, [0, 2]] + rng.normal(0, 0.05, (frames, 2))).astype(np.float32),
        gaze=rng.uniform(-1, 1, frames).astype(np.float32),
        speaking=rng.random(frames) < 0.4, valid=valid,
        root_position=root_position.astype(np.float32),
        root_rotation=root_rotation.astype(np.float32),
        audio={"logmel": rng.normal(size=(frames, D)).astype(np.float32)} if audio else {})


def make_sequence(rng, name, split, frames, invalid_a=(), invalid_b=(), audio=True):
    return ProcessedSequence(name=name, session=f"c--{name}", split=split, persons=(
        make_person(rng, "AAA111", frames, invalid_a, audio),
        make_person(rng, "BBB222", frames, invalid_b, audio)))


def write_folder(root: Path, sequences) -> None:
    attrs = shard_attrs(JOINT_NAMES[:J], V, {"logmel": {"n_mels": D}})
    infos, entries = [], {}
    for split in ("train", "val", "test"):
        with ShardWriter(root, split, attrs) as writer:
            for seq in sequences:
                if seq.split == split:
                    writer.add(seq)
        infos += writer.close()
        entries.update(writer.entries)
    write_manifest(root / MANIFEST_NAME, Manifest(
        toolkit_version="0.1.0", config={}, splits={}, shards=infos, sequences=entries))


def corpus(seed=0, eval_seed=None):
    rng = np.random.default_rng(seed)
    train = [
        # both-tracked runs [0,300) [320,700) [705,1000)
        make_sequence(rng, "seq-a", "train", 1000, invalid_a=[(300, 320)], invalid_b=[(700, 705)]),
        make_sequence(rng, "seq-b", "train", 250),
        make_sequence(rng, "seq-short", "train", 80),
        make_sequence(rng, "seq-gappy", "train", 300, invalid_a=[(i, i + 1) for i in range(50, 300, 60)]),
        make_sequence(rng, "seq-noaudio", "train", 200, audio=False),
    ]
    rng = np.random.default_rng(seed if eval_seed is None else eval_seed)
    return train + [make_sequence(rng, "seq-v", "val", 300, invalid_b=[(10, 20)]),
                    make_sequence(rng, "seq-t", "test", 220)]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    sequences = corpus()
    write_folder(root, sequences)
    return root, {s.name: s for s in sequences}


def both_valid(seq):
    return np.logical_and(seq.persons[0].valid, seq.persons[1].valid)


def check_item(item, seqs, window=W):
    """The item is an all-tracked window of its sequence, normalized to the agent's root."""
    seq = seqs[item["sequence"]]
    agent = [p.name for p in seq.persons].index(item["agent"])
    a, u = seq.persons[agent], seq.persons[1 - agent]
    start = int(item["start"])
    frames = slice(start, start + window)
    assert both_valid(seq)[frames].all() and start + window <= seq.frames
    assert item["motion"].shape == (window, J * 36 + V * 3) and item["motion"].dtype == torch.float32

    ico = item["motion"][:, :J * 36].numpy().reshape(window, J, 12, 3)
    positions, rotations = icosahedron.decode(ico)
    np.testing.assert_allclose(positions[0, 0, [0, 2]], 0, atol=1e-5)  # pelvis at the origin
    np.testing.assert_allclose(positions[0, 0, 1], a.root_position[start, 1], atol=1e-5)
    forward = rotations[0, 0, :, 2]  # pelvis facing direction
    assert abs(forward[0]) < 1e-4 and forward[2] > 0.9

    # The per-point transform in float64 is the reference: items match it to float32 rounding.
    tf = window_transform(a.root_position[start], a.root_rotation[start])
    expected = np.concatenate([tf.apply_points(a.icosahedra[frames].astype(np.float64)).reshape(window, -1),
                               tf.apply_points(a.shell[frames].astype(np.float64)).reshape(window, -1)], 1)
    np.testing.assert_allclose(item["motion"].numpy(), expected, rtol=0, atol=1e-5)
    np.testing.assert_allclose(item["user_head"].numpy(), tf.apply_floor(u.head[frames].astype(np.float64)),
                               rtol=0, atol=1e-5)
    np.testing.assert_array_equal(item["transform"].numpy(), tf.as_array())

    back = WindowTransform.from_array(item["transform"].numpy())
    np.testing.assert_allclose(back.invert_points(ico), a.icosahedra[frames], atol=1e-4)
    shell = item["motion"][:, J * 36:].numpy().reshape(window, V, 3)
    np.testing.assert_allclose(back.invert_points(shell), a.shell[frames], atol=1e-4)
    np.testing.assert_allclose(back.invert_floor(item["user_head"].numpy()), u.head[frames], atol=1e-4)
    np.testing.assert_array_equal(item["gaze"].numpy(), a.gaze[frames])
    np.testing.assert_array_equal(item["agent_speaking"].numpy(), a.speaking[frames])
    np.testing.assert_array_equal(item["user_speaking"].numpy(), u.speaking[frames])
    np.testing.assert_array_equal(item["agent_audio"].numpy(), a.audio["logmel"][frames])
    np.testing.assert_array_equal(item["user_audio"].numpy(), u.audio["logmel"][frames])


def test_window_start_helpers():
    valid = np.ones(20, bool)
    valid[[5, 6, 15]] = False
    assert tracked_runs(valid) == [(0, 5), (7, 15), (16, 20)]
    brute = [s for s in range(20 - 3 + 1) if valid[s:s + 3].all()]
    assert valid_starts(valid, 3).tolist() == brute
    assert sliding_starts(valid, 3).tolist() == [0, 7, 10, 16]
    assert valid_starts(valid, 21).size == 0 and tracked_runs(np.zeros(4, bool)) == []


def test_items_are_tracked_normalized_windows(folder):
    root, seqs = folder
    ds = WindowDataset(root, "train", window=W, length=40, seed=3)
    assert (ds.motion_dim, ds.audio_dim) == (J * 36 + V * 3, D)
    assert [(name, agent) for name, agent, _ in ds.pairs] == [
        ("seq-a", 0), ("seq-a", 1), ("seq-b", 0), ("seq-b", 1)]
    for index in range(len(ds)):
        item = ds[index]
        assert (item["sequence"], ["AAA111", "BBB222"].index(item["agent"])) == ds.pairs[index % 4][:2]
        check_item(item, seqs)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), epoch=st.integers(0, 1000), index=st.integers(0, 999))
def test_any_random_window_is_valid(folder, seed, epoch, index):
    root, seqs = folder
    ds = WindowDataset(root, "train", window=W, length=1000, seed=seed)
    ds.set_epoch(epoch)
    name, agent, start = ds.locate(index)
    assert start in valid_starts(both_valid(seqs[name]), W)
    check_item(ds[index], seqs)


def test_skipped_sequences_are_logged(folder, caplog):
    root, _ = folder
    with caplog.at_level(logging.WARNING, logger="sarah_data.dataset"):
        ds = WindowDataset(root, "train", window=W)
    reasons = dict(ds.skipped)
    assert sorted(reasons) == ["seq-gappy", "seq-noaudio", "seq-short"]
    assert "longest tracked run 59 of 300 frames" in reasons["seq-gappy"]
    assert "longest tracked run 80 of 80 frames" in reasons["seq-short"]
    assert reasons["seq-noaudio"] == "no audio features 'logmel'"
    assert "skipping sequence seq-gappy" in caplog.text
    motion_only = WindowDataset(root, "train", extractor=None, window=W)
    assert "seq-noaudio" in {name for name, _, _ in motion_only.pairs}
    assert "agent_audio" not in motion_only[0] and "motion" in motion_only[0]
    with pytest.raises(ValueError, match="no usable window"):
        WindowDataset(root, "train", window=1001, length=10)


def test_random_windows_are_reproducible_per_seed_and_epoch(folder):
    root, _ = folder
    make = lambda seed: WindowDataset(root, "train", window=W, length=64, seed=seed)  # noqa: E731
    a, b = make(0), make(0)
    starts = lambda ds: [ds.locate(i) for i in range(len(ds))]  # noqa: E731
    assert starts(a) == starts(b)
    assert starts(a) != starts(make(1))
    before = starts(a)
    a.set_epoch(1)
    assert starts(a) != before
    b.set_epoch(1)
    assert starts(a) == starts(b)
    with pytest.raises(IndexError):
        a[64]


def test_sliding_windows_tile_tracked_runs(folder):
    root, seqs = folder
    ds = WindowDataset.sliding(root, "train", window=W)
    assert ds.deterministic and len(ds) == 2 * (3 + 3 + 2) + 2 * 2  # seq-a runs of 300, 380, 295
    located = [ds.locate(i) for i in range(len(ds))]
    assert located == [ds.locate(i) for i in range(len(ds))]
    for name in ("seq-a", "seq-b"):
        for agent in (0, 1):
            starts = [s for n, a, s in located if (n, a) == (name, agent)]
            expected = [s for r0, r1 in tracked_runs(both_valid(seqs[name]))
                        for s in range(r0, r1 - W + 1, W)]
            assert starts == expected and np.all(np.diff(starts) >= W)
    for index in range(len(ds)):
        check_item(ds[index], seqs)
    with pytest.raises(ValueError):
        WindowDataset(root, "train", window=W, length=3, deterministic=True)


def test_default_window_is_400(folder, tmp_path):
    root, seqs = folder
    ds = WindowDataset(root, "train")
    assert ds.window == 400 and [(n, a) for n, a, _ in ds.pairs] == []  # no 400-frame tracked run
    val = WindowDataset(root, "val")  # seq-v: tracked [0,300) for 10-20 missing -> nothing either
    assert len(val) == 0 and ds.skipped[0][0] == "seq-a"
    long_root = tmp_path
    rng = np.random.default_rng(11)
    seq = make_sequence(rng, "seq-long", "train", 900, invalid_b=[(420, 430)])
    write_folder(long_root, [seq])
    long = WindowDataset(long_root, "train", length=6)
    for index in range(len(long)):
        check_item(long[index], {"seq-long": seq}, window=400)
        start = long.locate(index)[2]
        assert start <= 20 or 430 <= start <= 500


def test_batched_items_equal_single_items_and_collate_without_copying(folder):
    root, seqs = folder
    ds = WindowDataset(root, "train", window=W, length=12, seed=7)
    indices = [5, 0, 11, 3]
    items = ds.__getitems__(indices)
    assert [ds.locate(i) for i in indices] == [(x["sequence"], ["AAA111", "BBB222"].index(x["agent"]),
                                               x["start"]) for x in items]
    for index, item in zip(indices, items):
        check_item(item, seqs)
        single = ds[index]
        assert single.keys() == item.keys()
        for key, value in single.items():
            assert torch.equal(value, item[key]) if isinstance(value, torch.Tensor) else value == item[key]

    batch, reference = collate_windows(items), torch.utils.data.default_collate(items)
    assert batch.keys() == reference.keys()
    for key, value in reference.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(batch[key], value), key
        else:
            assert batch[key] == value, key
    # the items are rows of the batch tensors, which collate_windows returns as they are
    assert batch["motion"].data_ptr() == items[0]["motion"].data_ptr()
    assert batch["user_audio"].data_ptr() == items[0]["user_audio"].data_ptr()
    # items of separate calls are not rows of one tensor: collated like default_collate
    separate = [ds[i] for i in indices]
    copied = collate_windows(separate)
    assert torch.equal(copied["motion"], batch["motion"])
    assert all(copied["motion"].data_ptr() != item["motion"].data_ptr() for item in separate)
    assert collate_windows(separate[::-1])["start"].tolist() == [x["start"] for x in separate[::-1]]
    assert collate_windows(items[1:])["motion"].data_ptr() != items[1]["motion"].data_ptr()
    # rows of a tensor the dataset did not make for the batch are copied, never aliased
    own = torch.arange(6.0).reshape(2, 3)
    foreign = collate_windows([{"motion": own[0]}, {"motion": own[1]}])["motion"]
    assert torch.equal(foreign, own) and foreign.data_ptr() != own.data_ptr()


def test_batches_leave_the_intra_op_thread_count_as_it_was(folder):
    root, seqs = folder
    ds = WindowDataset(root, "train", window=W, length=4, seed=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the loader runs its windows on one thread, then restores this
    try:
        items = ds.__getitems__([0, 1, 2, 3])
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    for item in items:
        check_item(item, seqs)


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), x=st.floats(-5, 5), z=st.floats(-5, 5),
       frames=st.integers(1, 9), seed=st.integers(0, 2**16))
def test_window_motion_is_the_rigid_transform_on_one_blas_thread(yaw, x, z, frames, seed):
    from threadpoolctl import threadpool_info

    rng = np.random.default_rng(seed)
    ico, shell = rng.normal(size=(frames, 3, 12, 3)), rng.normal(size=(frames, 5, 3))
    transform = WindowTransform(yaw, x, z)
    points = homogeneous_points(ico, shell)
    blas_before = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    out = torch.full((frames, 41 * 3), np.nan)
    assert window_motion(points, transform, out=out) is out
    expected = points.astype(np.float64) @ transform.matrix().astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(out.numpy().reshape(frames, 41, 3), expected, rtol=1e-5, atol=1e-5)
    assert [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"] == blas_before
    with pytest.raises(ValueError, match="contiguous"):
        window_motion(points, transform, out=torch.empty((frames, 41 * 3 * 2))[:, ::2])


def test_normalize_window_is_the_item_transform(folder):
    root, seqs = folder
    ds = WindowDataset(root, "train", window=W, length=4, seed=1)
    for index in range(len(ds)):
        item = ds[index]
        a, u = [p for p in seqs[item["sequence"]].persons], None
        agent = [p.name for p in a].index(item["agent"])
        a, u = a[agent], a[1 - agent]
        frames = slice(item["start"], item["start"] + W)
        motion, head, transform = normalize_window(a.icosahedra[frames], a.shell[frames], u.head[frames],
                                                   a.root_position[item["start"]],
                                                   a.root_rotation[item["start"]])
        assert motion.dtype == head.dtype == np.float32
        np.testing.assert_array_equal(motion, item["motion"].numpy())
        np.testing.assert_array_equal(head, item["user_head"].numpy())
        np.testing.assert_array_equal(transform, item["transform"].numpy())


def test_split_is_read_whole_at_the_first_item_unless_too_large(tmp_path):
    copy = tmp_path / "shards"
    write_folder(copy, corpus())
    cached = WindowDataset(copy, "train", window=W, length=8, seed=2)
    untouched = WindowDataset(copy, "train", window=W, length=8, seed=2)
    streamed = WindowDataset(copy, "train", window=W, length=8, seed=2, cache_bytes=0)
    assert cached.in_memory and not streamed.in_memory
    expected = [streamed[i] for i in range(8)]
    streamed.shards.close()
    assert cached[0]["sequence"] == expected[0]["sequence"] == "seq-a"  # and reads seq-b too
    for path in copy.glob("train-*.h5"):
        path.rename(path.with_suffix(".moved"))
    # forked workers share what the parent read: none of them opens the (now missing) files
    loader = torch.utils.data.DataLoader(cached, batch_size=4, num_workers=2, collate_fn=collate_windows,
                                         multiprocessing_context="fork")
    got = _collect(loader)
    assert len(got) == len(expected)
    for x, y in zip(got, expected):
        for key, value in y.items():
            if isinstance(value, torch.Tensor):
                np.testing.assert_allclose(x[key].numpy(), value.numpy(), rtol=0, atol=1e-6, err_msg=key)
            else:
                assert x[key] == value, key
    for lazy in (streamed, untouched):
        with pytest.raises((OSError, ShardError)):
            lazy[0]


def _collect(loader):
    items = []
    for batch in loader:
        for i in range(len(batch["sequence"])):
            items.append({k: (v[i] if not isinstance(v, list) else v[i]) for k, v in batch.items()})
    return items


def _rows_collated(items):
    """collate_windows, failing (also inside a worker) unless it could skip the copy."""
    batch = collate_windows(items)
    assert all(batch[key].data_ptr() == items[0][key].data_ptr()
               for key in batch if isinstance(batch[key], torch.Tensor) and key != "start")
    return batch


def test_dataloader_workers_return_the_same_items(folder):
    root, _ = folder
    ds = WindowDataset(root, "train", window=W, length=12, seed=5)
    ds.set_epoch(2)
    ds[0]  # a file handle open in the parent must not leak into the forked workers
    single = _collect(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=0))
    runs = [_collect(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2)),
            _collect(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=0,
                                                 collate_fn=_rows_collated)),
            _collect(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2,
                                                 collate_fn=_rows_collated))]
    for multi in runs:
        assert len(single) == len(multi) == 12
        for x, y in zip(single, multi):
            assert x.keys() == y.keys()
            for key in x:
                if isinstance(x[key], torch.Tensor):
                    assert torch.equal(x[key], y[key]), key
                else:
                    assert x[key] == y[key]
    # what a spawned worker receives: the pickled dataset, without open files
    clone = pickle.loads(pickle.dumps(ds))
    assert clone.shards._handles == {}
    assert all(torch.equal(clone[i]["motion"], ds[i]["motion"]) for i in range(3))


def brute_force_stats(sequences, window):
    motions, heads, audio, bones = [], [], [], []
    for seq in sorted((s for s in sequences if s.split == "train"), key=lambda s: s.name):
        both = both_valid(seq)
        runs, start = [], None
        for t, ok in enumerate(list(both) + [False]):
            if ok and start is None:
                start = t
            if not ok and start is not None:
                runs.append((start, t))
                start = None
        for agent, user in (seq.persons, seq.persons[::-1]):
            for r0, r1 in runs:
                for s in range(r0, r1, window):
                    e = min(s + window, r1)
                    tf = window_transform(agent.root_position[s], agent.root_rotation[s])
                    motions.append(np.concatenate([tf.apply_points(agent.icosahedra[s:e]).reshape(e - s, -1),
                                                   tf.apply_points(agent.shell[s:e]).reshape(e - s, -1)], 1))
                    heads.append(tf.apply_floor(user.head[s:e]))
            if agent.audio:
                audio.append(agent.audio["logmel"][both])
            joints = agent.icosahedra[both].mean(axis=-2)  # pelvis, left hip, right hip
            bones.append(np.linalg.norm(joints[:, 1:] - joints[:, :1], axis=-1))
    out = {}
    for key, parts in (("motion", motions), ("user_head", heads), ("audio/logmel", audio),
                       ("bone_length", bones)):
        x = np.concatenate(parts).astype(np.float64)
        out[f"{key}/mean"], out[f"{key}/std"] = x.mean(0), x.std(0)
    return out


def test_stats_match_the_documented_procedure(tmp_path):
    sequences = corpus()
    for person in sequences[1].persons:
        person.audio["logmel"][:, 2] = 0.25  # a constant channel in seq-b
    write_folder(tmp_path, sequences)
    stats = compute_stats(tmp_path, window=W, epsilon=1e-4)
    assert stats.keys() == {"motion/mean", "motion/std", "user_head/mean", "user_head/std",
                            "audio/logmel/mean", "audio/logmel/std", "bone_length/mean",
                            "bone_length/std"}
    assert stats["motion/mean"].shape == (J * 36 + V * 3,) and stats["user_head/std"].shape == (2,)
    expected = brute_force_stats(sequences, W)
    for key, value in expected.items():
        np.testing.assert_allclose(stats[key], value, rtol=1e-5, atol=1e-6, err_msg=key)
    only_constant = [s for s in sequences if s.name == "seq-b"]
    write_folder(tmp_path / "b", only_constant)
    assert compute_stats(tmp_path / "b", window=W)["audio/logmel/std"][2] == np.float32(1e-4)
    for key, value in load_stats(tmp_path).items():
        np.testing.assert_array_equal(value, stats[key])


def test_stats_use_train_only_and_are_reproducible(tmp_path):
    write_folder(tmp_path / "a", corpus(seed=0, eval_seed=1))
    write_folder(tmp_path / "b", corpus(seed=0, eval_seed=2))  # other val/test values
    digest = lambda p: hashlib.sha256((p / STATS_NAME).read_bytes()).hexdigest()  # noqa: E731
    compute_stats(tmp_path / "a", window=W)
    first = digest(tmp_path / "a")
    compute_stats(tmp_path / "a", window=W)
    compute_stats(tmp_path / "b", window=W)
    assert digest(tmp_path / "a") == first == digest(tmp_path / "b")
    with pytest.raises(ShardError, match="no normalization statistics"):
        load_stats(tmp_path)
