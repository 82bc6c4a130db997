"""Inference speed-ups by module replacement (see ``optimize.py``): the reference model in
``sarah_models.nn`` never imports this package."""

from .cpu import cpu_identity, cpu_info, vector_isa
from .optimize import (
                       DECODER_PRECISIONS,
                       MODE_HELP,
                       MODES,
                       optimize_for_inference,
                       resolve_decoder,
                       warm_up,
)
from .threads import ThreadPolicy

__all__ = ["DECODER_PRECISIONS", "MODES", "MODE_HELP", "cpu_identity", "cpu_info",
           "optimize_for_inference", "resolve_decoder", "vector_isa", "warm_up", "ThreadPolicy"]
