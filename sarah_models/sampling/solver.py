"""The ODE solver of generation (A.3): its time grid, midpoint and Euler steps, and imputation.

Flow time tau runs from 0 (noise) to 1 (data) on the grid tau_i = i/n, h = 1/n. The midpoint
method takes, per step, v1 = v(z, tau_i), z_mid = z + h/2 v1, v2 = v(z_mid, tau_i + h/2),
z <- z + h v2 (2 network evaluations per step: 4 steps = 8 NFE); "euler" takes
z <- z + h v(z, tau_i). ``time_grid`` lists the flow times at which the network is evaluated,
computed by the same ``stage_times`` the solver steps through (inference caches per-tau terms
for exactly these values).

Imputation (3.3): every token k gets its noise eps_k once. While k is history, before every
network evaluation at flow time tau its state is replaced by z_tau = tau z_k + (1 - tau) eps_k
(eq. 4, ``path.interpolate``) with z_k its final predicted latent; only the newest token is
integrated. Reusing a token's own eps keeps the imputed state on the straight path from that
token's start to its end.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator

import torch
from torch import Tensor

from .path import interpolate

Velocity = Callable[[Tensor, float], Tensor]
Impute = Callable[[Tensor, float], Tensor]


def stage_times(steps: int, solver: str) -> Iterator[tuple[float, float, float | None]]:
    """Per solver step: (tau_i, h, the midpoint's tau or None for Euler)."""
    h = 1.0 / steps
    for i in range(steps):
        tau = i * h
        yield tau, h, (tau + 0.5 * h if solver == "midpoint" else None)


def time_grid(steps: int, solver: str) -> list[float]:
    """The flow times at which the solver evaluates the network, in order."""
    return [t for tau, _, mid in stage_times(steps, solver) for t in (tau, mid) if t is not None]


@functools.cache
def replay_times(steps: int, solver: str) -> tuple[float, ...]:
    """The flow times of a token's recorded trajectory: every evaluation's, then 1 (its final
    latent)."""
    return (*time_grid(steps, solver), 1.0)


def token_noise(generator: torch.Generator, latent_dim: int, scale: float) -> Tensor:
    """The noise eps_k of one new token (CPU float32), ``scale`` (``StreamConfig.noise_scale``)
    times a standard normal draw. Streaming and offline draw it token by token in the same
    order, so one seed gives both the same noise on any device. The scaled eps is the token's
    start and, while it is history, the noise end of its imputed path: one straight line."""
    return torch.randn(latent_dim, generator=generator, dtype=torch.float32) * scale


def imputer(noise: Tensor, known: Tensor | None) -> Impute:
    """Eq. 4 imputation: the first m tokens set to tau * known + (1 - tau) * eps."""
    m = 0 if known is None else known.shape[-2]

    def impute(z: Tensor, tau: float) -> Tensor:  # tokens on axis -2 (a stream axis may lead)
        if m == 0:
            return z
        return torch.cat((interpolate(noise[..., :m, :], known, tau), z[..., m:, :]), dim=-2)
    return impute


def replayer(states: Tensor | None, config) -> Impute:
    """Trajectory imputation: the first m tokens set to the state each held at flow time tau
    when it was solved. states (..., m, len(replay_times), Dz), the times in ``replay_times``
    order (a stream axis may lead); None or m = 0 imputes nothing."""
    m = 0 if states is None else states.shape[-3]
    times = replay_times(config.steps, config.solver)

    def impute(z: Tensor, tau: float) -> Tensor:
        if m == 0:
            return z
        return torch.cat((states.select(-2, times.index(tau)), z[..., m:, :]), dim=-2)
    return impute


def integrate(velocity: Velocity, noise: Tensor, impute: Impute, config,
              trace: list[Tensor] | None = None) -> Tensor:
    """tau from 0 to 1 in ``config.steps`` steps of ``config.solver``, imputing before every
    evaluation; ``config`` is a ``StreamConfig`` (or anything with steps and solver). A ``trace``
    list receives the state at every time of ``replay_times``: what each evaluation saw, then
    the result."""
    record = (lambda z: z) if trace is None else (lambda z: trace.append(z) or z)
    z = noise.clone()
    for tau, h, mid in stage_times(config.steps, config.solver):
        z = record(impute(z, tau))
        if mid is not None:
            z_mid = record(impute(z + 0.5 * h * velocity(z, tau), mid))
            z = z + h * velocity(z_mid, mid)
        else:
            z = z + h * velocity(z, tau)
    return record(impute(z, 1.0))
