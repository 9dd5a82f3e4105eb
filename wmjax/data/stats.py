"""Per-dataset action statistics: computed once per split and spec, cached as JSON beside the
data (:func:`wmjax.data.sources.action_stats`), carried by checkpoints so that rollouts of new
actions use the training normalisation.

Normalisation modes: ``mean_std`` -> ``(a - mean) / std``; ``bounds`` -> ``p01, p99`` mapped to
``[-1, 1]`` and clipped; ``none``. The gripper dimension (absolute open / close) is left alone.
"""

from __future__ import annotations

import dataclasses

import numpy as np

NORMALIZATIONS = ("mean_std", "bounds", "none")


@dataclasses.dataclass(frozen=True)
class ActionStats:
  """Statistics of a dataset's standardised actions ``[A]`` each."""

  dataset: str
  count: int
  mean: np.ndarray
  std: np.ndarray
  p01: np.ndarray
  p99: np.ndarray
  min: np.ndarray
  max: np.ndarray
  gripper_dim: int | None = None

  @classmethod
  def compute(cls, actions: np.ndarray, dataset: str, gripper_dim: int | None) -> "ActionStats":
    """From all actions ``[N, A]`` of a dataset."""
    actions = np.asarray(actions, np.float64)
    if actions.ndim != 2 or len(actions) == 0:
      raise ValueError(f"action statistics need actions [N, A] with N > 0, got {actions.shape}")
    p01, p99 = np.percentile(actions, [1, 99], axis=0)
    return cls(dataset, len(actions), actions.mean(0), actions.std(0), p01, p99, actions.min(0),
               actions.max(0), gripper_dim)

  @property
  def action_dim(self) -> int:
    return len(self.mean)

  def normalize(self, actions, mode: str = "mean_std", pad_to: int | None = None, xp=np):
    """Normalised ``actions [..., A]`` (float32); the gripper dimension is passed through.
    ``pad_to``: zero-pad the last axis to a model's (larger) action dimension. ``xp``: the array
    module (``numpy``, or ``jax.numpy`` inside jitted code)."""
    if mode not in NORMALIZATIONS:
      raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {mode!r}")
    actions = xp.asarray(actions, xp.float32)
    if actions.shape[-1] != self.action_dim:
      raise ValueError(f"actions have dimension {actions.shape[-1]}, the statistics of "
                       f"{self.dataset} {self.action_dim}")
    if mode == "none":
      out = actions
    elif mode == "mean_std":
      out = (actions - self.mean) / np.maximum(self.std, 1e-6)
    else:
      span = np.maximum(self.p99 - self.p01, 1e-6)
      out = xp.clip(2.0 * (actions - self.p01) / span - 1.0, -1.0, 1.0)
    if self.gripper_dim is not None and mode != "none":
      out = xp.where(np.arange(self.action_dim) == self.gripper_dim, actions, out)
    out = out.astype(xp.float32)
    if pad_to is not None and pad_to > out.shape[-1]:
      out = xp.pad(out, [(0, 0)] * (out.ndim - 1) + [(0, pad_to - out.shape[-1])])
    return out

  def affine(self, mode: str = "mean_std") -> tuple[np.ndarray, np.ndarray]:
    """``(shift, scale)`` ``[A]`` each with ``raw = shift + scale * normalised``: the inverse of
    :meth:`normalize` (inside the ``bounds`` range, which that mode clips to)."""
    if mode not in NORMALIZATIONS:
      raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {mode!r}")
    shift, scale = np.zeros(self.action_dim), np.ones(self.action_dim)
    if mode == "mean_std":
      shift, scale = self.mean, np.maximum(self.std, 1e-6)
    elif mode == "bounds":
      scale = np.maximum(self.p99 - self.p01, 1e-6) / 2
      shift = self.p01 + scale
    if self.gripper_dim is not None and mode != "none":
      shift = np.where(np.arange(self.action_dim) == self.gripper_dim, 0.0, shift)
      scale = np.where(np.arange(self.action_dim) == self.gripper_dim, 1.0, scale)
    return shift.astype(np.float32), scale.astype(np.float32)

  def to_dict(self) -> dict:
    out = dataclasses.asdict(self)
    for key, value in out.items():
      if isinstance(value, np.ndarray):
        out[key] = value.tolist()
    return out

  @classmethod
  def from_dict(cls, data: dict) -> "ActionStats":
    fields = {f.name for f in dataclasses.fields(cls)}
    missing = fields - set(data) - {"gripper_dim"}
    if missing:
      raise ValueError(f"action statistics lack {sorted(missing)}")
    arrays = {k: np.asarray(data[k], np.float64) for k in ("mean", "std", "p01", "p99", "min", "max")}
    return cls(dataset=data["dataset"], count=int(data["count"]),
               gripper_dim=data.get("gripper_dim"), **arrays)
