"""The body-model layer: SMPL-X parameters -> joints, global rotations, shell points, eyes, head points.

`BodyModel` runs a SMPL-X-format model file (a licensed SMPLX_NEUTRAL.npz or the procedural body
model from `write_procedural_body_model`) over Embody 3D's per-frame parameters.
"""

from sarah_data.body.model import BodyFrames, BodyModel, BodyModelError
from sarah_data.body.procedural import SOLE_Y, write_procedural_body_model
from sarah_data.body.shell import farthest_point_sampling, shell_vertex_ids

__all__ = ["BodyFrames", "BodyModel", "BodyModelError", "SOLE_Y", "farthest_point_sampling",
           "shell_vertex_ids", "write_procedural_body_model"]
