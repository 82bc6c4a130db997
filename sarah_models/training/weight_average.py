"""An exponential moving average of the trained module's weights (``train.ema_decay``).

Not in the paper, whose A.2 lists no average; DiT and most diffusion and flow models sample with
one (DiT: 0.9999 over 400k+ steps), because the last iterate of a noisy optimisation sits a
random step away from where the loss is low, and an average over many steps is closer. After
every optimizer step each floating-point entry of the module's state dict moves toward the
trained one:

    average <- average + (1 - d_t) (trained - average),   d_t = min(decay, (1 + t) / (10 + t))

where t counts the updates from 0. The warm-up of d_t (the rule of diffusers' ``EMAModel``)
keeps the first steps' random weights from lingering in a short run: a 190-step decoder stage
at decay 0.999 would otherwise keep 83 % of its starting point. Frozen weights (an encoder
under ``train.freeze_encoder``) stay bit for bit what they were: an average of equal values.

A checkpoint holds the average under the stage's own key (what generation, model files and
``--init-from`` read) and the trained weights under ``"trained"``, which only ``--resume``
reads (``stages.train``).
"""

from __future__ import annotations

from typing import Mapping

import torch
from torch import Tensor, nn

def decay_at(update: int, decay: float) -> float:
    """d_t of the ``update``-th update (0-based): the warmed-up decay."""
    return min(decay, (1.0 + update) / (10.0 + update))


class WeightAverage:
    """The running average of ``module``'s floating-point state, updated in place by ``update``."""

    def __init__(self, module: nn.Module, decay: float, updates: int = 0) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"the weight average's decay must be in (0, 1), got {decay}")
        self.module, self.decay, self.updates = module, decay, updates
        self.average = {name: value.detach().clone()
                        for name, value in module.state_dict().items() if value.is_floating_point()}
        # The module's own tensors, which the optimizer updates in place: read every step
        # without building a state dict.
        live = module.state_dict()
        self._pairs = [(self.average[name], live[name]) for name in self.average]

    @torch.no_grad()
    def update(self) -> None:
        weight = 1.0 - decay_at(self.updates, self.decay)
        for average, trained in self._pairs:
            average.lerp_(trained, weight)
        self.updates += 1

    def state_dict(self) -> dict[str, Tensor]:
        """The module's state dict with the averaged entries in place of the trained ones."""
        return {name: self.average[name].clone() if name in self.average else value.clone()
                for name, value in self.module.state_dict().items()}

    def load_average(self, state: Mapping[str, Tensor]) -> None:
        """Continue from a saved average (``state_dict``'s entries, the module's layout)."""
        for name, value in self.average.items():
            value.copy_(state[name])
