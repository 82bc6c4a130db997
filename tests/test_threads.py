"""The thread policy: others' load read from /proc/stat, one thread given up per busy core."""

from __future__ import annotations

import os
import sys

import pytest
import torch

from sarah_bench.load import BackgroundLoad
from sarah_models.accel.threads import ThreadPolicy, read_cpu_seconds, usable_cpus


def write_stat(path, ticks_per_cpu: dict[int, tuple[int, int, int]]) -> None:
    """A /proc/stat with per-CPU (busy user ticks, idle ticks, steal ticks)."""
    lines = ["cpu  0 0 0 0 0 0 0 0 0 0"]
    for cpu, (user, idle, steal) in ticks_per_cpu.items():
        lines.append(f"cpu{cpu} {user} 0 0 {idle} 0 0 0 {steal} 0 0")
    path.write_text("\n".join(lines) + "\nintr 1 2 3\n")


def test_rule_gives_up_one_thread_per_busy_core(monkeypatch):
    monkeypatch.setattr("sarah_models.accel.threads.usable_cpus", lambda: [0, 1, 2, 3])
    policy = ThreadPolicy(settle_s=0)
    assert [policy.threads_for(c) for c in (0.0, 0.29, 0.31, 1.0, 1.3, 1.31, 2.5, 9.0)] == \
        [4, 4, 3, 3, 3, 2, 1, 1]
    assert policy.threads == 4  # before any measurement: every usable core


def test_reads_busy_and_steal_of_our_cpus_only(tmp_path):
    stat = tmp_path / "stat"
    write_stat(stat, {0: (100, 900, 5), 1: (300, 700, 0), 2: (1000, 0, 0)})
    hz = os.sysconf("SC_CLK_TCK")
    assert read_cpu_seconds([0, 1], str(stat)) == pytest.approx(405 / hz)
    assert read_cpu_seconds([0, 1], str(tmp_path / "missing")) is None


def test_others_load_drops_and_restores_threads(tmp_path, monkeypatch):
    monkeypatch.setattr("sarah_models.accel.threads.usable_cpus", lambda: [0, 1])
    clock = {"wall": 100.0, "ours": 5.0}
    monkeypatch.setattr("sarah_models.accel.threads.time.monotonic", lambda: clock["wall"])
    monkeypatch.setattr("sarah_models.accel.threads.time.process_time", lambda: clock["ours"])
    hz = os.sysconf("SC_CLK_TCK")
    stat = tmp_path / "stat"
    busy = {0: 0, 1: 0}

    def advance(seconds: float, ours: float, others: float) -> int:
        clock["wall"] += seconds
        clock["ours"] += ours * seconds
        busy[0] += round(hz * (ours + others) * seconds)
        write_stat(stat, {cpu: (b, 0, 0) for cpu, b in busy.items()})
        return policy.update()

    write_stat(stat, {0: (0, 0, 0), 1: (0, 0, 0)})
    policy = ThreadPolicy(settle_s=0, interval_s=0.5, stat_path=str(stat))
    assert advance(1.0, ours=2.0, others=0.0) == 2
    assert advance(1.0, ours=1.0, others=1.0) == 1  # a busy neighbour: one thread
    assert policy.others_cores == pytest.approx(1.0, abs=0.05)
    assert advance(0.1, ours=1.0, others=0.0) == 1  # not re-measured before interval_s
    assert advance(1.0, ours=2.0, others=0.1) == 2  # it left: every core again


def test_fixed_threads_are_never_changed(tmp_path):
    policy = ThreadPolicy(threads=3, stat_path=str(tmp_path / "missing"))
    assert not policy.automatic and policy.update() == 3 and "fixed" in policy.describe()
    with pytest.raises(ValueError, match="threads must be >= 1"):
        ThreadPolicy(threads=0)


def test_without_proc_stat_every_core_is_kept(tmp_path):
    policy = ThreadPolicy(stat_path=str(tmp_path / "missing"), settle_s=0.01)
    assert policy.update() == len(usable_cpus())


def test_apply_sets_this_threads_torch_count(tmp_path):
    before = torch.get_num_threads()
    try:
        policy = ThreadPolicy(threads=1)
        torch.set_num_threads(2)
        assert policy.apply() == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/stat")
def test_a_real_busy_process_is_seen_and_its_core_given_up():
    cpus = usable_cpus()
    with BackgroundLoad(1, max_seconds=30) as load:
        assert load.running() == 1
        policy = ThreadPolicy(settle_s=0)
        policy.measure(0.6)
    assert policy.others_cores >= 0.5, policy.describe()
    assert policy.threads == max(1, len(cpus) - 1) or len(cpus) > 2
    assert load.running() == 0


def test_calibration_interleaves_the_counts_so_drift_does_not_decide(tmp_path, monkeypatch):
    """Two threads are truly 1 ms faster per chunk, but the machine slows by 0.5 ms with every
    call (a shared VM's speed drifts): timed one count after the other, two threads would come
    out slower; taking turns, they come out faster and become the ceiling."""
    monkeypatch.setattr("sarah_models.accel.threads.usable_cpus", lambda: [0, 1])
    write_stat(tmp_path / "stat", {0: (0, 0, 0), 1: (0, 0, 0)})
    policy = ThreadPolicy(settle_s=0, stat_path=str(tmp_path / "stat"))
    clock = {"now": 0.0, "calls": 0}
    monkeypatch.setattr("sarah_models.accel.threads.time.perf_counter", lambda: clock["now"])
    before = torch.get_num_threads()

    def chunk() -> None:
        clock["calls"] += 1
        clock["now"] += (0.010 if torch.get_num_threads() == 1 else 0.009) + 0.0005 * clock["calls"]

    medians = policy.calibrate(chunk, calls=6, warm=2)
    assert clock["calls"] == 16 and torch.get_num_threads() == before
    assert set(medians) == {1, 2} and medians[2] < medians[1]
    assert policy.ceiling == 2 and policy.threads == 2
