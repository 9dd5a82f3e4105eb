"""Learnable policies: a :class:`wmjax.nn.policy.FramePolicy` with its parameters, its action
normalisation and the action dimensions it controls, as one pytree that owns saving and loading.

A :class:`LearnedPolicy` is called like every wmjax policy, ``policy(frames [B, c, H, W, 3] in
[-1, 1], key) -> raw actions [B, k, A]``, so it plugs into :class:`wmjax.env.WorldModelEnv`
(through :func:`wmjax.eval.policy_eval.env_episodes`), :func:`wmjax.eval.policy_eval.scan_episodes`
and a task's true environment. It is a pytree whose leaves are arrays (parameters and
normalisation), so a jitted rollout takes it as an argument: a policy with new parameters runs the
program the old one compiled (:func:`split_policy`).

  policy = LearnedPolicy.create(model.action_stats, "mean_std", context=1, chunk=1,
                                frame_shape=(16, 16, 3), key=jax.random.key(0))
  policy.save("policies/start"); policy = load_policy("policies/start")
"""

from __future__ import annotations

import json
import os
from typing import Any, Callable, Sequence

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from wmjax.data.stats import ActionStats
from wmjax.nn.policy import FramePolicy

POLICY_FILE = "policy.json"


@flax.struct.dataclass
class LearnedPolicy:
  """A frame policy: ``module`` maps the newest ``context`` frames to a Gaussian over ``chunk``
  normalised actions; ``raw = shift + scale * normalised`` (the training data's statistics),
  clipped to ``[low, high]`` (the range the data covers); the dimensions not in ``controls`` are
  0. ``temperature`` scales the sampled noise (0: the mean action, what evaluation uses)."""

  module: FramePolicy = flax.struct.field(pytree_node=False)
  params: Any
  shift: jax.Array
  scale: jax.Array
  low: jax.Array
  high: jax.Array
  context: int = flax.struct.field(pytree_node=False)
  controls: tuple[bool, ...] = flax.struct.field(pytree_node=False)
  temperature: float = flax.struct.field(pytree_node=False, default=0.0)

  @classmethod
  def create(cls, stats: ActionStats, normalization: str, *, context: int, chunk: int,
             frame_shape: Sequence[int], key: jax.Array, controls: Sequence[bool] | None = None,
             **module_fields) -> "LearnedPolicy":
    """A new policy (random parameters) for frames ``frame_shape (H, W, 3)`` and the actions of
    ``stats``, normalised as the world model's data (``normalization``)."""
    if context < 1 or chunk < 1:
      raise ValueError(f"context and chunk must be >= 1, got {context} and {chunk}")
    if len(frame_shape) != 3 or frame_shape[-1] != 3:
      raise ValueError(f"frame_shape must be (H, W, 3), got {tuple(frame_shape)}")
    a = stats.action_dim
    controls = (True,) * a if controls is None else tuple(bool(c) for c in controls)
    if len(controls) != a:
      raise ValueError(f"controls must name all {a} action dimensions, got {len(controls)}")
    module = FramePolicy(action_dim=a, chunk=chunk, **module_fields)
    params = jax.jit(module.init)(key, jnp.zeros((1, context) + tuple(frame_shape)))["params"]
    shift, scale = stats.affine(normalization)
    return cls(module, params, jnp.asarray(shift), jnp.asarray(scale),
               jnp.asarray(stats.min, jnp.float32), jnp.asarray(stats.max, jnp.float32),
               context, controls)

  @property
  def chunk(self) -> int:
    return self.module.chunk

  def distribution(self, params: Any, frames: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean ``[B, k, A]`` and log standard deviation ``[A]`` of the normalised actions after
    ``frames [B, c, H, W, 3]`` under ``params`` (what training differentiates)."""
    if frames.ndim != 5 or frames.shape[1] != self.context:
      raise ValueError(f"the policy reads [B, {self.context}, H, W, 3] frames, got "
                       f"{tuple(frames.shape)}")
    return self.module.apply({"params": params}, frames)

  def __call__(self, frames: jax.Array, key: jax.Array) -> jax.Array:
    """Raw actions ``[B, k, A]`` after ``frames [B, c, H, W, 3]`` (in [-1, 1]); compiled once
    per policy structure and frame shape, also when called from the host step by step."""
    return _act(self, jnp.asarray(frames, jnp.float32), key)

  def normalize(self, raw: jax.Array) -> jax.Array:
    """Raw actions ``[..., A]`` -> the normalised actions the module predicts."""
    return (raw - self.shift) / self.scale

  def with_temperature(self, temperature: float) -> "LearnedPolicy":
    return self.replace(temperature=float(temperature))

  def save(self, directory: str, info: dict | None = None) -> None:
    """Write the policy to a new ``directory``: ``params/`` (orbax) beside ``policy.json`` (the
    module's fields, normalisation, controls and ``info``, e.g. how it was trained)."""
    directory = os.path.abspath(os.path.expanduser(directory))
    if os.path.exists(directory):
      raise FileExistsError(f"{directory} exists; a policy is written to a new directory")
    checkpointer = ocp.StandardCheckpointer()
    checkpointer.save(os.path.join(directory, "params"), self.params)
    checkpointer.wait_until_finished()
    description = {
        "module": {"action_dim": self.module.action_dim, "chunk": self.module.chunk,
                   "channels": list(self.module.channels), "hidden": self.module.hidden},
        "context": self.context, "controls": list(self.controls),
        **{k: np.asarray(getattr(self, k)).tolist() for k in ("shift", "scale", "low", "high")},
        "info": info or {}}
    with open(os.path.join(directory, POLICY_FILE), "w") as f:
      json.dump(description, f, indent=2)


@jax.jit
def _act(policy: LearnedPolicy, frames: jax.Array, key: jax.Array) -> jax.Array:
  mean, log_std = policy.distribution(policy.params, frames)
  normalised = mean + policy.temperature * jnp.exp(log_std) * jax.random.normal(key, mean.shape)
  raw = jnp.clip(policy.shift + policy.scale * normalised, policy.low, policy.high)
  return jnp.where(jnp.asarray(policy.controls), raw, 0.0)


def load_policy(directory: str) -> LearnedPolicy:
  """The policy :meth:`LearnedPolicy.save` wrote to ``directory`` (temperature 0)."""
  directory = os.path.abspath(os.path.expanduser(directory))
  path = os.path.join(directory, POLICY_FILE)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{directory} holds no {POLICY_FILE}: not a policy written by "
                            f"LearnedPolicy.save (wmjax clone-policy / wmjax improve)")
  with open(path) as f:
    description = json.load(f)
  module = FramePolicy(**description["module"])
  params = ocp.StandardCheckpointer().restore(os.path.join(directory, "params"))
  arrays = {k: jnp.asarray(description[k], jnp.float32) for k in ("shift", "scale", "low", "high")}
  return LearnedPolicy(module, params, context=description["context"],
                       controls=tuple(description["controls"]), **arrays)


def split_policy(policy: Callable) -> tuple[Any, list]:
  """What a compiled rollout is keyed on and what it takes as arguments: a policy that is a
  pytree of arrays (a :class:`LearnedPolicy`) -> (its tree structure, its arrays), so new
  parameters reuse the program; any other callable -> (itself, []), compiled in as a constant."""
  leaves, treedef = jax.tree.flatten(policy)
  if leaves and all(isinstance(x, (jax.Array, np.ndarray)) for x in leaves):
    return treedef, leaves
  return policy, []


def join_policy(static: Any, leaves: list) -> Callable:
  """The policy :func:`split_policy` split (inside the compiled function, ``leaves`` traced)."""
  if isinstance(static, jax.tree_util.PyTreeDef):
    return jax.tree.unflatten(static, leaves)
  return static
