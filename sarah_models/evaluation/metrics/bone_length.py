"""Bone-length error: how far a clip's bones stretch or shrink, in percent (p95).

Generated motion is a set of icosahedra, not a rigid skeleton: nothing forces a bone to keep
its length. Per bone (a body joint and its parent) and frame, the length's relative deviation
from the bone's median length over the clip; the clip's value is the 95th percentile over
frames and bones. Real motion scores ~0 (only the fit's noise).
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import BODY_JOINTS, JOINT_PARENTS
from sarah_data.skeleton import bone_lengths

from .spec import Metric



def bone_length_error(joint_positions, percentile: float = 95.0) -> float:
    """The ``percentile`` of |length / median length - 1| over frames and body bones, in %."""
    lengths = bone_lengths(joint_positions, [(j, JOINT_PARENTS[j]) for j in range(1, BODY_JOINTS)
                                             if JOINT_PARENTS[j] >= 0])
    median = np.median(lengths, axis=0)
    keep = median > 1e-6
    relative = np.abs(lengths[:, keep] / median[keep] - 1.0)
    return float(np.percentile(relative, percentile) * 100.0)


METRIC = Metric(name="bone_length", label="Bone Len.", kind="clip", order=60, unit="% (p95)",
                decimals=1, better="lower",
                function=lambda clip, config: bone_length_error(clip.joints[0]))
