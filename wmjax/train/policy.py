"""Training a :class:`wmjax.policy.LearnedPolicy`: behaviour cloning from a world model's dataset
and fitting to any (weighted) set of decisions.

A decision is what the policy saw and what it did: ``frames [c, H, W, 3]`` in [-1, 1] and the
normalised ``actions [k, A]`` that followed. The loss is the Gaussian negative log-likelihood of
the actions in the dimensions the policy controls, weighted per decision (filtered behaviour
cloning keeps weights 0 / 1, reward-weighted regression ``exp(return / beta)``).

  policy = LearnedPolicy.create(model.action_stats, "mean_std", context=1, chunk=1,
                                frame_shape=(16, 16, 3), key=jax.random.key(0))
  policy, losses = fit_policy(policy, demonstrations(model.config, policy, 64), steps=500)
  # the same for a loaded world model, its rollout context and frames, from the training
  # episodes a control task clones from (None: all):
  policy, losses = clone_policy(model, task.controls, steps=500, keep=task.demonstration)
"""

from __future__ import annotations

import functools
from typing import Callable, Iterable, Iterator

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax

from wmjax.data.pipeline import WindowSource, training_pipeline
from wmjax.data.rlds import Episode
from wmjax.data.sources import open_dataset
from wmjax.frames import to_model
from wmjax.model import LoadedModel
from wmjax.policy import LearnedPolicy


def demonstrations(config: ml_collections.ConfigDict, policy: LearnedPolicy, batch_size: int,
                   seed: int = 0, keep: Callable[[Episode], bool] | None = None
                   ) -> Iterator[dict[str, np.ndarray]]:
  """Endless batches of the decisions in the training split of a world model's dataset
  (``config``: the model's config), read by the same pipeline and normalised as the model
  reads them: ``frames [B, c, H, W, 3]``, ``actions [B, k, A]``. ``keep``: which training
  episodes to read, asked of each episode's first step (default all; a control task's
  ``demonstration``)."""
  if config.data.get("latents_dir") or config.data.get("mixture"):
    raise ValueError("behaviour cloning reads one dataset of frames; this config reads "
                     "pre-encoded latents or a mixture")
  dataset = open_dataset(config.data)
  split = dataset.split(config.data.train_split)
  if split.spec.action_dim != policy.module.action_dim:
    raise ValueError(f"{split.spec.name} has {split.spec.action_dim}-dim actions, the "
                     f"policy {policy.module.action_dim}")
  lengths = split.lengths()  # 0 for an episode without the spec's camera
  episodes = None if keep is None else [
      i for i in range(len(split)) if lengths[i] and keep(split.episode(i, 0, 1))]
  if episodes == []:
    raise ValueError(f"no training episode of {split.builder_dir} is a demonstration to clone")
  c, k = policy.context, policy.chunk
  source = WindowSource(split, c + k, 1, dataset.resolution(split.spec), only=episodes)
  batches = training_pipeline([source], [dataset.train_stats()], batch_size=batch_size, seed=seed,
                              normalization=config.data.normalization)
  for batch in batches:
    yield {"frames": to_model(batch["frames"][:, :c]), "actions": batch["actions"][:, c - 1:c - 1 + k]}


def decision_batches(frames: np.ndarray, actions: np.ndarray, weights: np.ndarray,
                     batch_size: int, seed: int = 0) -> Iterator[dict[str, np.ndarray]]:
  """Endless shuffled batches of the decisions ``frames [N, c, H, W, 3]``, normalised ``actions
  [N, k, A]`` with ``weights [N]``; decisions of weight 0 are left out."""
  kept = np.flatnonzero(np.asarray(weights) > 0)
  if not len(kept):
    raise ValueError("no decision has a positive weight")
  rng = np.random.default_rng(seed)
  size = min(batch_size, len(kept))  # every batch the same shape: one compiled update
  while True:
    order = rng.permutation(kept)
    for first in range(0, len(order) - size + 1, size):
      index = order[first:first + size]
      yield {"frames": frames[index], "actions": actions[index], "weights": weights[index]}


def policy_loss(policy: LearnedPolicy, params, batch: dict) -> jax.Array:
  """Weighted mean Gaussian negative log-likelihood (per controlled dimension, constants left
  out) of ``batch['actions'] [B, k, A]`` after ``batch['frames']``."""
  mean, log_std = policy.distribution(params, batch["frames"])
  z = (batch["actions"] - mean) * jnp.exp(-log_std)
  nll = 0.5 * z ** 2 + log_std  # [B, k, A]
  controls = jnp.asarray(policy.controls, jnp.float32)
  per_decision = (nll * controls).sum((-2, -1)) / (controls.sum() * mean.shape[1])
  weights = batch.get("weights", jnp.ones(per_decision.shape[0]))
  return (weights * per_decision).sum() / jnp.maximum(weights.sum(), 1e-9)


@functools.lru_cache(maxsize=8)
def _update_fn(structure, learning_rate: float):
  """The jitted Adam step for one policy structure: (policy's arrays, optimizer state, batch) ->
  (new arrays, new state, loss)."""
  optimizer = optax.adam(learning_rate)

  @jax.jit
  def update(policy_leaves, opt_state, batch):
    policy = jax.tree.unflatten(structure, policy_leaves)
    loss, grads = jax.value_and_grad(functools.partial(policy_loss, policy))(policy.params, batch)
    updates, opt_state = optimizer.update(grads, opt_state, policy.params)
    params = optax.apply_updates(policy.params, updates)
    return jax.tree.leaves(policy.replace(params=params)), opt_state, loss

  return update


def fit_policy(policy: LearnedPolicy, batches: Iterable[dict], steps: int,
               learning_rate: float = 1e-3) -> tuple[LearnedPolicy, np.ndarray]:
  """``steps`` Adam steps of :func:`policy_loss` on ``batches`` from ``policy``'s parameters;
  the fitted policy and the loss of every step ``[steps]``."""
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  leaves, structure = jax.tree.flatten(policy)
  update = _update_fn(structure, float(learning_rate))
  opt_state = optax.adam(learning_rate).init(policy.params)
  losses = []
  for _, batch in zip(range(steps), batches):
    leaves, opt_state, loss = update(leaves, opt_state, jax.tree.map(jnp.asarray, batch))
    losses.append(loss)
  return jax.tree.unflatten(structure, leaves), np.asarray(jax.device_get(losses))


def clone_policy(model: LoadedModel, controls, *, steps: int, chunk: int = 1,
                 batch_size: int = 64, learning_rate: float = 1e-3, seed: int = 0,
                 keep: Callable[[Episode], bool] | None = None
                 ) -> tuple[LearnedPolicy, np.ndarray]:
  """A new policy for ``model`` (its frames, action statistics and rollout context) setting the
  action dimensions ``controls`` (None: all), behaviour-cloned for ``steps`` steps from the
  training episodes of the model's dataset that ``keep`` keeps (default all;
  :func:`demonstrations`); the policy and the loss of every step."""
  policy = LearnedPolicy.create(model.action_stats, model.config.data.normalization,
                                context=model.config.rollout.context, chunk=chunk,
                                frame_shape=model.image_shape, key=jax.random.key(seed),
                                controls=controls)
  return fit_policy(policy, demonstrations(model.config, policy, batch_size, seed, keep),
                    steps, learning_rate)
