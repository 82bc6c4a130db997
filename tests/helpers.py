"""Shared test builders (owner: evaluation). Small shards with several splits, reusing the
person builder of test_generate so every test writes shards the same way; and what the
benchmarks' tests look for after a run (busy processes left behind)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

from sarah_data import icosahedron
from sarah_data.constants import JOINT_NAMES
from sarah_data.shards import (MANIFEST_NAME, Manifest, ProcessedSequence, ShardAttrs,
                               ShardWriter, write_manifest)
from test_generate import SHELL, make_person


def shard_attrs(joint_names=JOINT_NAMES, shell_points: int = SHELL,
                extractors: dict | None = None) -> ShardAttrs:
    """Root attributes of a test shards folder (procedural body, unit icosahedron)."""
    return ShardAttrs(toolkit_version="0.1.0", joint_names=tuple(joint_names),
                      icosahedron_template=icosahedron.TEMPLATE,
                      icosahedron_radius=icosahedron.DEFAULT_RADIUS,
                      shell_vertex_ids=np.arange(shell_points), body_model_name="procedural",
                      body_model_sha256="0" * 64, extractors=extractors or {})


def randomize(model, seed: int, scale: float, add: bool = False):
    """Seeded N(0, scale) weights everywhere (or added to the current ones), in eval mode:
    zero-initialised gates would otherwise hide any dependence on the inputs."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            noise = torch.randn(p.shape, generator=g) * scale
            p.add_(noise) if add else p.copy_(noise)
    return model.eval()


def write_split_shards(root: Path, sequences: dict[str, int], frames: int = 40,
                       features: tuple[str, ...] = ("logmel",), seed: int = 0,
                       shell_points: int = SHELL) -> dict[str, list[ProcessedSequence]]:
    """A shards folder with ``sequences[split]`` two-person sequences of ``frames`` frames per
    split (one session each; both persons tracked except the last 4 frames, random motion
    around a slowly walking root, random audio features). Returns the sequences per split."""
    if shell_points != SHELL:
        raise ValueError(f"make_person writes {SHELL} shell points")
    rng = np.random.default_rng(seed)
    attrs = shard_attrs(JOINT_NAMES, shell_points, {f: {} for f in features})
    infos, entries, splits, written = [], {}, {}, {}
    for split, count in sequences.items():
        splits[split] = []
        written[split] = []
        with ShardWriter(root, split, attrs) as writer:
            for n in range(count):
                session = f"c--{split}--{n:04d}"
                seq = ProcessedSequence(
                    name=f"{session}--seq", session=session, split=split,
                    persons=(make_person(rng, f"A{split[:2].upper()}{n:03d}", frames, features),
                             make_person(rng, f"B{split[:2].upper()}{n:03d}", frames, features)))
                writer.add(seq)
                splits[split].append(session)
                written[split].append(seq)
            infos += writer.close()
            entries.update(writer.entries)
    write_manifest(root / MANIFEST_NAME, Manifest(toolkit_version="0.1.0", config={},
                                                  splits=splits, shards=infos, sequences=entries))
    return written


def spinning_processes() -> list[str]:
    """Process ids of ``sarah_bench.load.BackgroundLoad`` busy loops still running."""
    spinning = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if b"while time.monotonic() < end" in cmdline.read_bytes():
                spinning.append(cmdline.parent.name)
        except OSError:  # a process that ended while we looked
            pass
    return spinning


def load_script(name: str) -> ModuleType:
    """scripts/NAME.py imported as module NAME (scripts are not a package). It is registered in
    sys.modules first, where dataclasses look their module up."""
    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
