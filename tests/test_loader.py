"""WindowLoader: the batches of WindowDataset.__getitems__, bit for bit, in reused shared slots."""

import gc
import os
import signal
import time
from contextlib import contextmanager
from dataclasses import replace

import pytest
import torch

from sarah_data.dataset import WindowDataset, collate_windows
from sarah_data.loader import LoaderError, WindowLoader
from test_dataset import W, corpus, write_folder

LENGTH, BATCH = 22, 4  # 5 full batches and one of 2


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    path = tmp_path_factory.mktemp("loader_shards")
    write_folder(path, corpus())
    return path


@pytest.fixture
def dataset(root):
    return WindowDataset(root, "train", window=W, length=LENGTH, seed=3)


@contextmanager
def deadline(seconds: int):
    """Fail (instead of hanging) when the block takes longer than `seconds`."""
    def alarm(*_):
        raise TimeoutError(f"took more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def expected(dataset, indices):
    return collate_windows(dataset.__getitems__(indices))


def assert_same_batch(got, want):
    assert got.keys() == want.keys()
    for key, value in want.items():
        if isinstance(value, torch.Tensor):
            assert got[key].dtype == value.dtype and torch.equal(got[key], value), key
        else:
            assert got[key] == value, key


def shared_maps() -> int:
    with open("/proc/self/maps") as maps:
        return sum("/dev/shm/torch_" in line for line in maps)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.parametrize("workers", [0, 2])
def test_batches_equal_getitems_in_order(dataset, workers):
    dataset.set_epoch(1)
    batches = [[5, 0, 21], [3, 3, 9, 12], [17], list(range(6, 10)), [1, 2]]
    with deadline(30), WindowLoader(dataset, batches, workers=workers) as loader:
        assert loader.batch_size == 4 and len(loader) == len(batches)
        count = 0
        for indices, batch in zip(batches, loader):  # each compared before the next is asked
            assert_same_batch(batch, expected(dataset, indices))
            count += 1
        assert count == len(batches)
    with deadline(30), WindowLoader(dataset, BATCH, workers=workers) as loader:
        sizes = []
        for number, batch in enumerate(loader):
            indices = list(range(number * BATCH, min(LENGTH, (number + 1) * BATCH)))
            assert_same_batch(batch, expected(dataset, indices))
            sizes.append(len(batch["sequence"]))
        assert sizes == [4, 4, 4, 4, 4, 2] and len(loader) == 6
    assert len(WindowLoader(dataset, BATCH, drop_last=True)) == 5
    assert [len(b["sequence"]) for b in WindowLoader(dataset, BATCH, drop_last=True)] == [4] * 5


def test_zero_and_two_workers_give_identical_bits(dataset):
    dataset.set_epoch(4)
    runs = []
    for workers in (0, 2):
        with deadline(30), WindowLoader(dataset, 3, workers=workers, slots=2) as loader:
            runs.append([{k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in b.items()}
                         for b in loader])
    assert len(runs[0]) == len(runs[1]) == 8
    for a, b in zip(*runs):
        assert_same_batch(a, b)


@pytest.mark.parametrize("workers,slots", [(0, 1), (0, 2), (2, 3)])
def test_slots_are_reused_and_a_kept_batch_is_overwritten(dataset, workers, slots):
    with deadline(30), WindowLoader(dataset, BATCH, workers=workers, slots=slots) as loader:
        kept, pointers = [], []
        for batch in loader:
            kept.append((batch, batch["motion"].clone()))
            pointers.append({k: v.untyped_storage().data_ptr() for k, v in batch.items()
                             if isinstance(v, torch.Tensor) and k != "start"})
        assert len(pointers) == 6
        for number, pointer in enumerate(pointers):
            assert pointer == pointers[number % slots]  # the same slot storage comes back
            assert len({p["motion"] for p in pointers[number:number + slots]}) == min(
                slots, len(pointers) - number)  # and the slots in between are distinct
        # the contract: a batch is valid until the next one is requested; kept longer, its
        # slot holds a later batch (here: the last one that used the slot)
        for number, (batch, motion) in enumerate(kept):
            last = max(n for n in range(len(kept)) if n % slots == number % slots)
            rows = min(batch["motion"].shape[0], kept[last][1].shape[0])
            assert torch.equal(batch["motion"][:rows], kept[last][1][:rows])
            if last != number:
                assert not torch.equal(batch["motion"][:rows], motion[:rows])


def test_epoch_is_taken_when_an_iteration_starts(dataset):
    batches = [[0, 1, 2, 3], [4, 5, 6, 7]]
    with deadline(30), WindowLoader(dataset, batches, workers=2) as loader:
        seen = {}
        for epoch in (1, 2, 1):
            dataset.set_epoch(epoch)
            iterator = iter(loader)
            dataset.set_epoch(7)  # too late for this iteration, as with a DataLoader
            got = [b["start"].clone() for b in iterator]
            dataset.set_epoch(epoch)
            for indices, starts in zip(batches, got):
                assert torch.equal(starts, expected(dataset, indices)["start"])
            seen.setdefault(epoch, torch.cat(got))
            assert torch.equal(seen[epoch], torch.cat(got))
        assert not torch.equal(seen[1], seen[2])  # new windows each epoch


def test_a_new_iteration_ends_the_previous_one(dataset):
    with deadline(30), WindowLoader(dataset, BATCH, workers=2) as loader:
        first = iter(loader)
        next(first)
        second = iter(loader)  # waits for the first iteration's batches still being filled
        assert_same_batch(next(second), expected(dataset, [0, 1, 2, 3]))
        with pytest.raises(RuntimeError, match="newer iteration"):
            next(first)
        assert len(list(second)) == 5


def test_a_worker_exception_is_raised_with_its_traceback(dataset):
    batches = [[0, 1], [2, LENGTH + 5], [3]]  # index out of range in the second batch
    with deadline(30), WindowLoader(dataset, batches, workers=2) as loader:
        iterator = iter(loader)
        assert_same_batch(next(iterator), expected(dataset, [0, 1]))
        with pytest.raises(LoaderError, match=r"(?s)batch 1.*Traceback.*in locate.*IndexError"):
            next(iterator)
        # the loader survives a failing batch
        assert_same_batch(next(iter(loader.iter_batches([[7, 8]]))), expected(dataset, [7, 8]))
    with WindowLoader(dataset, batches, workers=0) as loader:
        with pytest.raises(IndexError):
            list(loader)
    with WindowLoader(dataset, 2, workers=0) as loader, pytest.raises(ValueError, match="fit"):
        next(iter(loader.iter_batches([[0, 1, 2]])))


def test_a_killed_worker_is_an_error_not_a_hang(dataset):
    with deadline(20), WindowLoader(dataset, 1, workers=2, slots=2) as loader:
        iterator = iter(loader)
        next(iterator)
        pids = loader.pids
        os.kill(pids[0], signal.SIGKILL)
        with pytest.raises(LoaderError, match="killed by signal 9"):
            for _ in iterator:
                pass
        assert loader.pids == [] and not any(alive(pid) for pid in pids)
        with pytest.raises(RuntimeError, match="closed"):
            iter(loader)
    with deadline(20), WindowLoader(dataset, 1, workers=2) as loader:  # killed between epochs
        list(loader)
        os.kill(loader.pids[1], signal.SIGKILL)
        with pytest.raises(LoaderError, match="worker 1"):
            list(loader)


class StuckDataset(WindowDataset):
    """A dataset whose batch with index 13 never finishes (a deadlocked worker)."""

    def fill(self, indices, out):
        if 13 in indices:
            time.sleep(60)
        return super().fill(indices, out)


def test_a_stuck_worker_times_out(root):
    stuck = StuckDataset(root, "train", window=W, length=LENGTH, seed=3)
    with deadline(20), WindowLoader(stuck, [[0], [13], [1]], workers=2, timeout=0.5) as loader:
        pids = loader.pids
        with pytest.raises(LoaderError, match="within 0.5 s"):
            list(loader)
        assert loader.pids == [] and not any(alive(pid) for pid in pids)


def test_close_leaves_no_process_and_no_shared_memory(dataset):
    dataset.load()
    gc.collect()  # loaders of earlier tests
    before = shared_maps()
    ways = ("close", "with", "del", "interrupt", "abandoned")
    for way in ways:
        with deadline(20):
            loader = WindowLoader(dataset, BATCH, workers=2)
            pids = loader.pids
            assert len(pids) == 2 and all(alive(pid) for pid in pids)
            assert shared_maps() > before
            iterator = iter(loader)
            batch = next(iterator)
            if way == "close":
                loader.close()
                loader.close()  # idempotent
            elif way == "with":
                with loader:
                    pass
            elif way == "del":
                del loader, iterator
                gc.collect()
            elif way == "interrupt":  # Ctrl-C while the main process waits for a batch
                with pytest.raises(KeyboardInterrupt):
                    iterator.throw(KeyboardInterrupt)
                assert loader.pids == []
            elif way == "abandoned":  # stopped early: no slot is left half-filled, workers stay
                iterator.close()
                assert loader._pending == {} and loader.pids == pids
                loader.close()
            del batch
            assert not any(alive(pid) for pid in pids), way
            assert shared_maps() == before, way


def test_training_batches_come_from_the_loader(root):
    from sarah_models.config import TrainConfig
    from sarah_models.training.batches import EpochBatches
    from sarah_models.training.distributed import DistInfo

    dataset = WindowDataset(root, "train", window=W, length=12, seed=0)
    config = replace(TrainConfig.tiny(), window=W, batch_size=4)
    info = DistInfo(0, 1, 0, torch.device("cpu"))
    plan = EpochBatches(dataset, config, info)
    want = [(e, indices) for e in range(2) for indices in plan.epoch_batches(e)]
    for workers in (0, 2):
        with deadline(30):
            batches = EpochBatches(dataset, replace(config, num_workers=workers), info,
                                   start_batch=1)
            iterator = iter(batches)
            for (epoch, indices), batch in zip(want[1:], iterator):
                dataset.set_epoch(epoch)  # (what the loader's workers were told)
                assert_same_batch(batch, expected(dataset, indices))
            iterator.close()  # stops the loader's workers


def test_training_steps_are_done_with_a_batch_before_the_next_is_requested(root):
    """With one slot and no worker, requesting a batch overwrites the previous one at once: a
    training loop that still used a batch after asking for the next would lose other values
    than one trained on copies."""
    from sarah_models.training.checkpoint import build_models
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.training.batches import EpochBatches
    from sarah_models.training.distributed import DistInfo
    from sarah_models.training.loop import make_optimizer, train_loop
    from sarah_models.training.objectives import FlowObjective, VAEObjective
    from test_train import tiny_config

    dataset = WindowDataset(root, "train", window=W, length=12, seed=0)
    config = tiny_config(4)
    config = replace(config, train=replace(config.train, window=W, num_workers=0))
    dims = {"motion": dataset.motion_dim, "audio": dataset.audio_dim}
    stats = {"motion": (torch.zeros(dims["motion"]), torch.ones(dims["motion"])),
             "user_head": (torch.zeros(2), torch.ones(2)),
             "audio": (torch.zeros(dims["audio"]), torch.ones(dims["audio"])),
             "latent": (torch.zeros(config.vae.latent_dim), torch.ones(config.vae.latent_dim))}
    info = DistInfo(0, 1, 0, torch.device("cpu"))
    runs = {}
    for copies in (False, True):
        losses = []
        for stage in ("vae", "flow"):
            torch.manual_seed(0)
            vae, flow = build_models(config, dims)
            objective = (VAEObjective(vae, Normalizer(stats)) if stage == "vae"
                         else FlowObjective(flow, vae, Normalizer(stats)))
            batches = EpochBatches(dataset, config.train, info)
            if copies:
                batches = ({k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in b.items()}
                           for b in batches)
            records = train_loop(objective, batches, make_optimizer(objective.trainable, config.train),
                                 config.train, total_steps=4)
            losses += [r["loss"] for r in records]
        runs[copies] = losses
    assert len(runs[False]) == 8 and runs[False] == runs[True]
