"""The paper's metrics (section 4) as a registry: one ``Metric`` per file of this folder.

FGD, FGD_acc (Fréchet distances of shell positions and accelerations), foot slide, wrist speed
and head angle; ``table.evaluate`` scores generated clips against ground truth with all of them.
Adding a metric is adding one file that sets ``METRIC = Metric(...)`` (``spec.py``).
"""

from sarah_data.moments import Moments

from .clips import Clip, DecodedClip, accelerations
from .foot_slide import foot_slide, foot_steps, step_paths, step_reaches
from .frechet import (
                      FrechetRidgeWarning,
                      FrechetTerms,
                      frechet_distance,
                      frechet_distance_from_moments,
                      frechet_terms,
                      moments_distance,
)
from .head_angle import head_angle
from .spec import Metric, MetricsConfig, registered
from .table import (
                      CategoryValues,
                      MetricsTable,
                      category_means,
                      clip_values,
                      evaluate,
                      metric_units,
                      reference_table,
)
from .wrist_speed import wrist_speed

METRICS = tuple(m.name for m in registered())

__all__ = ["METRICS", "CategoryValues", "Clip", "DecodedClip", "FrechetRidgeWarning", "FrechetTerms",
           "Metric", "MetricsConfig", "MetricsTable", "Moments", "accelerations", "category_means",
           "clip_values", "evaluate", "foot_slide", "foot_steps", "frechet_distance",
           "frechet_distance_from_moments", "frechet_terms", "head_angle", "metric_units",
           "moments_distance", "reference_table", "registered", "step_paths", "step_reaches",
           "wrist_speed"]
