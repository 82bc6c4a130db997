"""Models that ship with the package, by name: ``--pretrained NAME`` in ``sarah-generate``,
``sarah-serve`` and ``sarah-eval``, or ``model_path(NAME)`` in Python.

Each is a ``model.safetensors`` file (``training.model_file``: weights, normalizer and config,
loaded without pickle) written by the script named beside it, so anyone can train it again and
compare. The digest is checked on every load: a file damaged in transit, or a Git LFS pointer left
in its place, gets one clear line instead of a failure deep inside safetensors.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path


@dataclass(frozen=True)
class Pretrained:
    name: str
    file: str  # inside this package
    sha256: str
    script: str  # the repository's script that trains it, from nothing
    fixture_seed: int | None  # the sarah-fixtures seed of its training corpus (None: not fixtures)
    about: str  # one line for --help

    def describe(self) -> str:
        seed = "" if self.fixture_seed is None else f" (fixture seed {self.fixture_seed})"
        return f"{self.name}: {self.about}{seed}"


MODELS = {model.name: model for model in (
    Pretrained(
        name="fixture-tiny",
        file="fixture-tiny.safetensors",
        sha256="36656687177f24c86d953259a299aa495bee1cd995b46dc39a028176fa369450",
        script="scripts/pretrained_fixture_model.sh",
        fixture_seed=0,
        about="the tiny preset trained on 40 dyad-minutes of fixture dyads for about 125 "
              "CPU-minutes; docs/results.md has its figures on fixtures it never saw"),
)}


def names() -> list[str]:
    return sorted(MODELS)


def model_path(name: str) -> Path:
    """The checked file of a shipped model; ValueError with one line when it is unknown,
    missing or not the file that was shipped."""
    if name not in MODELS:
        raise ValueError(f"no pretrained model {name!r} (shipped: {', '.join(names())})")
    model = MODELS[name]
    path = Path(str(resources.files(__package__).joinpath(model.file)))
    if not path.is_file():
        raise ValueError(f"{path}: the pretrained model {name!r} is missing from this install "
                         f"({model.script} trains it)")
    return verified(path, model)


def verified(path: Path, model: Pretrained) -> Path:
    """``path`` when its bytes are the ones ``model`` shipped with, else ValueError."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != model.sha256:
        raise ValueError(f"{path}: sha256 {digest[:12]}..., expected {model.sha256[:12]}... "
                         f"(a damaged copy or a Git LFS pointer; reinstall, or retrain with "
                         f"{model.script})")
    return path
