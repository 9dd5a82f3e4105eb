"""Discrete noise schedules: ``betas [T]`` and cumulative signal ``alphas_cumprod [T]`` (float64).

Level ``i`` in ``[0, T-1]`` has signal ``abar[i] = prod_{k<=i} (1 - beta_k)``.
"""

from __future__ import annotations

import numpy as np

SCHEDULES = ("linear", "cosine", "sigmoid")


def linear_betas(num_timesteps: int = 1000, beta_start: float = 1e-4,
                 beta_end: float = 0.02) -> np.ndarray:
  """DDPM / DiT / IRASim linear betas; the end points scale with ``1000 / T`` as in DiT."""
  scale = 1000.0 / num_timesteps
  return np.linspace(scale * beta_start, scale * beta_end, num_timesteps, dtype=np.float64)


def betas_from_alpha_bar(alpha_bar: np.ndarray, max_beta: float = 0.999) -> np.ndarray:
  """``beta_i = clip(1 - abar(u_{i+1}) / abar(u_i), 0, max_beta)`` for a continuous ``abar`` on T+1 points."""
  return np.clip(1.0 - alpha_bar[1:] / alpha_bar[:-1], 0.0, max_beta)


def cosine_betas(num_timesteps: int = 1000, s: float = 0.008, max_beta: float = 0.999) -> np.ndarray:
  """Nichol & Dhariwal: ``abar(u) = cos((u + s) / (1 + s) * pi / 2)^2``."""
  u = np.linspace(0.0, 1.0, num_timesteps + 1, dtype=np.float64)
  return betas_from_alpha_bar(np.cos((u + s) / (1 + s) * np.pi / 2) ** 2, max_beta)


def sigmoid_betas(num_timesteps: int = 1000, start: float = -3.0, end: float = 3.0,
                  tau: float = 1.0, max_beta: float = 0.999) -> np.ndarray:
  """WPE sigmoid schedule: ``abar(u) = (sig(e/tau) - sig((u(e-s)+s)/tau)) / (sig(e/tau) - sig(s/tau))``."""
  sig = lambda z: 1.0 / (1.0 + np.exp(-z))
  u = np.linspace(0.0, 1.0, num_timesteps + 1, dtype=np.float64)
  v_start, v_end = sig(start / tau), sig(end / tau)
  alpha_bar = (v_end - sig((u * (end - start) + start) / tau)) / (v_end - v_start)
  return betas_from_alpha_bar(alpha_bar / alpha_bar[0], max_beta)


def make_betas(name: str, num_timesteps: int = 1000) -> np.ndarray:
  builders = {"linear": linear_betas, "cosine": cosine_betas, "sigmoid": sigmoid_betas}
  if name not in builders:
    raise ValueError(f"noise schedule must be one of {SCHEDULES}, got {name!r}")
  return builders[name](num_timesteps)


def alphas_cumprod(betas: np.ndarray) -> np.ndarray:
  return np.cumprod(1.0 - np.asarray(betas, np.float64))
