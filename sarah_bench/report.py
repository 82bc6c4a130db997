"""The bench's verdicts and outputs: goals met or missed, the plain-text report, the history
row of docs/performance.md and the JSON file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sarah_data.atomic import atomic_write_text

from .config import GOALS


def _node(results: dict[str, Any], key: str) -> Any:
    """The value at a dotted key (a goal's ``@target`` suffix ignored), or None if absent."""
    node: Any = results
    for part in key.split("@")[0].split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _lookup(results: dict[str, Any], key: str) -> float | None:
    node = _node(results, key)
    return None if node is None else float(node)


def _interval(results: dict[str, Any], key: str) -> list[float | None] | None:
    """The interval stored beside a percentile (``...p99`` -> ``...p99_interval``), if any."""
    return _node(results, key.split("@")[0] + "_interval")


def interval_text(interval: list[float | None] | None) -> str:
    """" (low-high)" of a percentile's interval; "?" for an end the sample could not bound."""
    if not interval:
        return ""
    low, high = (("?" if v is None else f"{v:,.1f}") for v in interval)
    return f" ({low}-{high})"


def check_goals(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Each goal of ``GOALS`` with its measured value (None when not measured) and verdict."""
    rows = []
    for key, text, target, kind in GOALS:
        value = _lookup(results, key)
        met = None if value is None else (value >= target if kind == "min" else value < target)
        rows.append({"goal": key, "description": text, "target": target, "kind": kind,
                     "value": value, "met": met, "interval": _interval(results, key)})
    return rows


def _deviation_text(label: str, dev: dict[str, float], reference: str = "fp32") -> str:
    return (f"{label} vs {reference} over {dev['frames']} frames: max joint {dev['max_joint_mm']:.3f} mm, "
            f"mean {dev['mean_joint_mm']:.3f} mm (motion scale {dev['motion_scale_mm']:.1f} mm), "
            f"head-angle delta {dev['head_angle_delta']:.4f}")


def _f(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or value != value else f"{value:,.{digits}f}"


def _fit(concurrent: dict[str, Any]) -> str:
    """How many streams held: ">= N" when even the largest count tried held."""
    return f"{'>= ' if concurrent.get('every_count_held') else ''}{concurrent['fit']}"


def cpu_text(env: dict[str, Any]) -> str:
    """The CPU as reports name it: model name and instruction set, then family, model and
    last-level cache where known (VMs of one model name differ there)."""
    return f"{env['cpu']}, {env['cpu_identity']}" if env.get("cpu_identity") else env["cpu"]


def format_report(results: dict[str, Any]) -> str:
    """The results as plain-text tables."""
    env = results["environment"]
    lines = [f"sarah-bench  {env['date']}  {cpu_text(env)}, {env['cores']} cores, "
             f"{env['threads']} threads, torch {env['torch']}",
             f"load average before {env['load_before'][0]:.2f}, after "
             f"{env.get('load_after', [float('nan')])[0]:.2f} "
             f"(other processes on these cores slow every figure down)", ""]
    prep = results.get("prep", {})
    if prep:
        lines += ["prep (dyad-seconds per wall-second)      fast    naive(-j 1)   ratio   "
                  "CPU ms per dyad-s, fast / naive"]
        for name, row in prep.items():
            lines.append(f"  {name:<14} -j {int(row['jobs'])}, {row['dyad_seconds']:.0f} dyad-s "
                         f"{_f(row['rtf']):>9}x {_f(row['naive_rtf']):>9}x   {_f(row['ratio'], 2)}"
                         f"    {_f(row.get('fast_cpu_ms_per_dyad_s'), 2)} / "
                         f"{_f(row.get('naive_cpu_ms_per_dyad_s'), 2)}")
    loader = results.get("loader")
    if loader:
        lines += ["", "loader (400-frame windows per second)   steady   with start-up   CPU ms/window"]
        rows = [(f"WindowLoader, {key.replace('_', ' ')}", loader[key]) for key in ("workers_0", "workers_2")]
        rows += [(f"DataLoader, {key.replace('_', ' ')} (reference)", loader[key]["dataloader"])
                 for key in ("workers_0", "workers_2") if "dataloader" in loader[key]]
        for label, row in rows:
            lines.append(f"  {label:<38}{_f(row['windows_per_s']):>8}  "
                         f"{_f(row['windows_per_s_with_startup']):>8}   "
                         f"{_f(row.get('cpu_ms_per_window'), 2):>13}")
        lines.append(f"  ratio 2 workers / 0 workers: {_f(loader['ratio'], 2)}")
    offline = results.get("offline", {})
    if offline:
        lines += ["", f"offline generation (fps = T / time, best of 3)   {results['config']['mode']}"
                      f"     fp32 plain   ratio"]
        for size, row in offline.items():
            lines.append(f"  {size:<44}{_f(row['fps']):>8}  {_f(row['naive_fps']):>10}   "
                         f"{_f(row['ratio'], 2)}")
    streaming = results.get("streaming", {})
    if streaming:
        cfg = results["config"]
        lines += ["", "streaming (chunks of 4 frames, midpoint x 4 = 8 NFE, cfg 1.3, logmel audio; "
                      f"fast = {cfg['mode']} flow, {cfg.get('decoder_precision', 'fp32')} decoder)"]
        header = (f"  {'':<16}{'fps':>8}  {'chunks':>6}  {'p50 ms':>8}  {'p99 ms (95 % interval)':>24}   "
                  f"stage p50/p99 ms: audio | flow | decode | other")
        lines.append(header)
        for size, row in streaming.items():
            variants = [(f"{size} fast", row), (f"{size} naive", row["naive"])]
            if "fewer_steps" in row:
                variants.append((f"{size} fast {2 * row['fewer_steps']['steps']} NFE",
                                 row["fewer_steps"]))
            for label, r in variants:
                st = r["stages_ms"]
                stage_text = " | ".join(f"{_f(st[k]['p50'])}/{_f(st[k]['p99'])}"
                                        for k in ("audio", "flow", "decode", "other"))
                latency = r["latency_ms"]
                p99 = _f(latency["p99"]) + interval_text(latency.get("p99_interval"))
                lines.append(f"  {label:<16}{_f(r['fps']):>8}  {latency.get('n', '-'):>6}  "
                             f"{_f(latency['p50']):>8}  {p99:>24}   {stage_text}")
            lines.append(f"  {size} ratio fast/naive {_f(row['ratio'], 2)}; "
                         f"{_deviation_text(results['config']['mode'], row['deviation'])}")
            if "deviation_shipped" in row:
                lines.append(f"  {size} on trained weights (the shipped fixture-tiny): " + _deviation_text(
                    results['config']['mode'], row['deviation_shipped']))
            if row.get("calibration_ms"):
                lines.append(f"  {size} thread calibration, chunk p50 ms by threads: " + ", ".join(
                    f"{k}: {_f(v)}" for k, v in row["calibration_ms"].items())
                    + f"; threads used {row.get('threads_used')}")
            if "deviation" in row.get("fewer_steps", {}):
                nfe = 2 * row["fewer_steps"]["steps"]
                text = _deviation_text(f"{nfe} NFE {results['config']['mode']}",
                                       row["fewer_steps"]["deviation"], "8 NFE fp32")
                lines.append(f"  {size} {text}"
                             f" (fewer steps change the output: quality in docs/results.md)")
    concurrent = results.get("concurrent", {})
    loaded = results.get("loaded", {})
    for size, row in concurrent.items():
        lines += ["", f"concurrent {size} streams in one process, one flow solve per round for all "
                      "(real time: >= 30 fps each and p99 round <= 133 ms)",
                  f"  {'streams':>8}  {'idle fps each':>14}  {'p99 round ms':>12}"
                  + (f"   {'loaded fps each':>15}  {'p99 round ms':>12}" if loaded else "")]
        loaded_row = loaded.get("concurrent", {}).get(size, {})
        loaded_rows = {r["streams"]: r for r in loaded_row.get("rows", [])}
        for r in row["rows"]:
            text = f"  {r['streams']:>8}  {_f(r['fps_each']):>14}  {_f(r['round_ms']['p99']):>12}"
            if r["streams"] in loaded_rows:
                lr = loaded_rows[r["streams"]]
                text += f"   {_f(lr['fps_each']):>15}  {_f(lr['round_ms']['p99']):>12}"
            lines.append(text)
        fit = f"  streams that hold real time: idle {_fit(row)}"
        if loaded_row:
            fit += f", under load {_fit(loaded_row)}"
        if "round_robin" in row:
            fit += f"; round robin (one solve per stream): idle {_fit(row['round_robin'])}"
            if "round_robin" in loaded_row:
                fit += f", under load {_fit(loaded_row['round_robin'])}"
        lines.append(fit)
        if "shipped" in row:
            text = (f"  the shipped fixture-tiny (trained, its decoding chain on), one solve per "
                    f"round: idle {_fit(row['shipped'])}")
            if "shipped" in loaded_row:
                text += f", under load {_fit(loaded_row['shipped'])}"
            rows_text = "; ".join(f"{r['streams']}: {_f(r['fps_each'])} fps each, p99 round "
                                  f"{_f(r['round_ms']['p99'])} ms" for r in row["shipped"]["rows"])
            lines += [text, f"    idle {rows_text}"]
    if loaded:
        lines += ["", f"under background load ({loaded['processes']} busy processes of the bench's "
                      "own), side by side with idle",
                  f"  {'figure':<34}{'idle':>10}  {'loaded':>10}   loaded / idle"]
        for size, row in loaded.get("streaming", {}).items():
            idle = results["streaming"][size]
            pairs = [(f"{size} stream fps", idle["fps"], row["fps"]),
                     (f"{size} chunk p50 ms", idle["latency_ms"]["p50"], row["latency_ms"]["p50"]),
                     (f"{size} chunk p99 ms", idle["latency_ms"]["p99"], row["latency_ms"]["p99"])]
            if "fewer_steps" in row and "fewer_steps" in idle:
                nfe = 2 * row["fewer_steps"]["steps"]
                pairs += [(f"{size} {nfe} NFE fps", idle["fewer_steps"]["fps"], row["fewer_steps"]["fps"]),
                          (f"{size} {nfe} NFE p99 ms", idle["fewer_steps"]["latency_ms"]["p99"],
                           row["fewer_steps"]["latency_ms"]["p99"])]
            if size in loaded.get("offline", {}):
                pairs.append((f"{size} offline fps", results["offline"][size]["fps"],
                              loaded["offline"][size]["fps"]))
            for label, a, b in pairs:
                lines.append(f"  {label:<34}{_f(a):>10}  {_f(b):>10}   {_f(b / a, 2)}")
            lines.append(f"  {size} chunk p99 95 % intervals: idle"
                         f"{interval_text(idle['latency_ms'].get('p99_interval'))}, loaded"
                         f"{interval_text(row['latency_ms'].get('p99_interval'))}")
            lines.append(f"  {size} threads used per chunk: idle {idle.get('threads_used')}, "
                         f"loaded {row.get('threads_used')}")
            fixed = row.get("fixed_threads")
            if fixed:
                lines.append(f"  {size} loaded with a fixed {fixed['threads']} threads: "
                             f"{_f(fixed['fps'])} fps, p50 {_f(fixed['latency_ms']['p50'])} ms, "
                             f"p99 {_f(fixed['latency_ms']['p99'])}"
                             f"{interval_text(fixed['latency_ms'].get('p99_interval'))} ms "
                             f"({fixed['frames']} frames)")
    rounds = results.get("rounds")
    if rounds:
        lines += ["", f"{rounds['count']} more rounds, each idle then beside {rounds['processes']} "
                      "busy processes: median (min-max)",
                  f"  {'figure':<26}{'idle':>24}  {'loaded':>24}"]
        for size in results["config"]["sizes"]:
            if size not in rounds:
                continue
            for key, label in (("fps", "stream fps"), ("p50_ms", "chunk p50 ms"),
                               ("p99_ms", "chunk p99 ms")):
                cells = [f"{_f(r['median'])} ({_f(r['min'])}-{_f(r['max'])})"
                         for r in (rounds[size]["idle"][key], rounds[size]["loaded"][key])]
                lines.append(f"  {size + ' ' + label:<26}{cells[0]:>24}  {cells[1]:>24}")
    kernel = results.get("kernel", {}).get("paper")
    if kernel:
        loaded_kernel = loaded.get("kernel", {}).get("paper", {})
        lines += ["", "one paper-size int8 Linear (1024 -> 4096, 6 rows), per call"
                      + (": idle | under load" if loaded_kernel else ""),
                  "  threads   p50 us   p99 us" + ("   | p50 us    p99 us" if loaded_kernel else "")]
        for threads, row in kernel.items():
            text = f"  {threads:>7}  {_f(1000 * row['p50'], 0):>7}  {_f(1000 * row['p99'], 0):>7}"
            if threads in loaded_kernel:
                lr = loaded_kernel[threads]
                text += f"   | {_f(1000 * lr['p50'], 0):>6}  {_f(1000 * lr['p99'], 0):>8}"
            lines.append(text)
    floors = results.get("memory_floor", {})
    if floors:
        lines += ["", "memory floor: the time merely to read one streamed chunk's weights (every "
                      "solver evaluation reads the flow's again); no kernel is faster"]
        for label, section in (("idle", results), ("under load", loaded)):
            for size, floor in section.get("memory_floor", {}).items():
                reads = ", ".join(f"{threads} thread{'s' * (threads != '1')} {_f(row['ms'], 2)} ms "
                                  f"({_f(row['fps'], 0)} fps)" for threads, row in floor["threads"].items())
                fps = section.get("streaming", {}).get(size, {}).get("fps")
                lines.append(f"  {size} {label}: {floor['megabytes']:,.0f} MB per chunk; read in {reads}; "
                             f"streamed {_f(fps)} fps")
    hubert = results.get("hubert_streaming")
    if hubert:
        lines += ["", "HuBERT-Large causal streaming: one pass per 4-frame chunk (133 ms of audio)",
                  "  window s   ms per chunk   x real time   fps"]
        for row in hubert:
            lines.append(f"  {row['window_s']:>8.1f}   {row['ms_per_chunk']:>12,.0f}   "
                         f"{row['realtime_factor']:>11.3f}   {row['fps']:>5.2f}")
    lines += ["", "goals"]
    width = max((len(goal["description"]) for goal in results.get("goals", [])), default=0)
    for goal in results.get("goals", []):
        verdict = {True: "MET", False: "MISSED", None: "not measured"}[goal["met"]]
        sign = ">=" if goal["kind"] == "min" else "<"
        value = _f(goal["value"]) + interval_text(goal.get("interval"))
        lines.append(f"  {goal['description']:<{width}} {value:>21}  {sign} {goal['target']:g}  {verdict}")
    lines.append(f"\nbench time {results['environment'].get('bench_seconds', 0):.0f} s")
    return "\n".join(lines)


def history_row(results: dict[str, Any]) -> str:
    """One line for the history table of docs/performance.md."""
    env = results["environment"]

    def get(key: str) -> str:
        value = _lookup(results, key)
        return _f(value)

    mode = results["config"]["mode"]
    if results["config"].get("decoder_precision") == "bf16":
        mode += ", bf16 decoder"
    return (f"| {env['date'][:10]} | {cpu_text(env)} | {env['threads']} | {env['torch']} | "
            f"{mode} | {get('streaming.paper.fps')} | "
            f"{get('streaming.paper.latency_ms.p99')} | "
            f"{get('streaming.paper.fewer_steps.latency_ms.p99')} | {get('offline.paper.fps')} | "
            f"{get('streaming.tiny.fps')} | {get('prep.logmel.rtf')} | "
            f"{get('loader.workers_2.windows_per_s')} | {env['load_before'][0]:.1f} |")


def write_json(path: Path, results: dict[str, Any]) -> None:
    """Write ``results`` to ``path`` via a temporary file and a rename."""
    atomic_write_text(path, json.dumps(results, indent=2, sort_keys=True) + "\n")


def append_history(path: Path, row: str) -> None:
    """Append ``row`` after the last line of the history table (the file's last table row)."""
    text = path.read_text() if path.exists() else ""
    lines = text.splitlines()
    last = max((i for i, line in enumerate(lines) if line.startswith("| ")), default=None)
    if last is None:
        lines += ["", row]
    else:
        lines.insert(last + 1, row)
    atomic_write_text(path, "\n".join(lines) + "\n")
