"""Screen: the T drawn open loop along the simulator's own episodes, with or without poses given.

    python experiments/pusht/open_loop_pose.py WORKDIR STEP OUT.json

Simulates ``eval-policy``'s held-out episodes of the default policies (the same start states,
keys and 8 actions), then rolls the world model of ``WORKDIR`` out open loop from the first two
frames along the simulator's actions. A model whose actions carry poses
(``experiments/pusht/pose_latents.py``) is given them as read off the *simulator's* frames: the
pose of the frame each action is taken at (8 action numbers more than 2: ``now``) and also that
of the frame it leads to (14: ``next``, an oracle of the T's dynamics). Writes the T's IoU, its
centroid and angle errors at every generated frame and per episode at the last.
"""

from __future__ import annotations

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.frames import to_model, to_uint8
from wmjax.model import load_model
from wmjax.rollout import rollout
from wmjax.tasks.pusht import simulator as pusht
from wmjax.tasks.pusht.evaluate import (_image_size, _params, initial_states,
                                        policies_from_specs, policy_chunk)
from wmjax.tasks.pusht.metrics import pusht_metrics
from wmjax.tasks.pusht.perception import perceived_state

EPISODES, STEPS = 48, 8
METRICS = ("block_iou", "block_error_px", "block_angle_error_deg", "agent_error_px")


def posed_actions(actions: np.ndarray, frames: np.ndarray, action_dim: int) -> np.ndarray:
  """``actions [B, N, 2]`` (action ``j`` moves frame ``j`` to ``j + 1`` of ``frames [B, N+1, ...]``)
  with the poses the model takes: none, the frame's (``now``) or also the next frame's."""
  if action_dim == 2:
    return actions
  state = np.asarray(perceived_state(to_model(jnp.asarray(frames), xp=jnp)))
  parts = [actions, state[:, :-1]] + ([state[:, 1:]] if action_dim == 14 else [])
  out = np.concatenate(parts, -1)
  if out.shape[-1] != action_dim:
    raise ValueError(f"cannot give a model of {action_dim} action numbers its poses")
  return out.astype(np.float32)


def main(workdir: str, step: str, out: str) -> None:
  model = load_model(workdir, step=int(step))
  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  action_dim = model.world_model.network.action_dim
  states = initial_states(config, EPISODES, "evaluate", 0)
  result = {"workdir": workdir, "step": int(step), "action_dim": action_dim, "policies": {}}
  for index, (name, policy) in enumerate(policies_from_specs(None, policy_chunk(config)).items()):
    truth = pusht.simulate_policy(policy, states, STEPS, image_size=_image_size(model),
                                  key=jax.random.fold_in(jax.random.key(0), index), context=c,
                                  action_repeat=_params(config).action_repeat)
    actions = posed_actions(truth["actions"], truth["frames"], action_dim)
    normed = model.action_stats.normalize(actions, config.data.normalization, pad_to=action_dim)
    rng = jax.random.fold_in(jax.random.key(1), index)
    window = model.codec.encode(to_model(jnp.asarray(truth["frames"][:, :c]), xp=jnp),
                                jax.random.split(rng)[1])
    latents = rollout(model.world_model, model.params, window, jnp.asarray(normed[:, c - 1:]),
                      rng, horizon=h, context_actions=jnp.asarray(normed[:, :c - 1]))
    imagined = to_uint8(np.asarray(model.codec.decode(latents[:, c:])))
    scores = pusht_metrics(imagined, truth["frames"][:, c:], {})
    result["policies"][name] = {
        "per_step": {m: [float(x) for x in scores[m].mean(0)] for m in METRICS},
        "end_per_episode": {m: [float(x) for x in scores[m][:, -1]] for m in METRICS}}
    print(name, {m: round(float(scores[m][:, -1].mean()), 3) for m in METRICS}, flush=True)
  with open(out, "w") as f:
    json.dump(result, f, indent=1)


if __name__ == "__main__":
  main(*sys.argv[1:])
