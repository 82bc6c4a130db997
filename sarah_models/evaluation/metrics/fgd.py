"""FGD: Fréchet distance of per-frame mesh-shell positions (V*3,) in the window frame, cm^2."""

from .spec import Metric

METRIC = Metric(name="fgd", label="FGD", kind="frechet", order=10, unit="{u}^2", length_power=2,
                scale=10.0, decimals=2, better="lower",
                function=lambda clip, config: clip.shell_window)
