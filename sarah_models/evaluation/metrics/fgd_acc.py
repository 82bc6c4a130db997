"""FGD_acc: Fréchet distance of the shell's per-frame accelerations
(x[t+1] - 2 x[t] + x[t-1]) * fps^2, in (cm/s^2)^2."""

from .clips import accelerations
from .spec import Metric

METRIC = Metric(name="fgd_acc", label="FGD_acc", kind="frechet", order=20, unit="({u}/s^2)^2",
                length_power=2, scale=1e5, decimals=2, better="lower",
                function=lambda clip, config: accelerations(clip.shell_window, clip.fps))
