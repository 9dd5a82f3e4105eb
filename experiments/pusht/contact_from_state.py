"""Push-T: can the T's next pose be learnt from what two frames show, with the data a world model has?

A world model of the ``latent`` profile draws the pushed T no better than copying the last frame
(``probe.py --split_by_motion``). This asks whether that is the data's limit or the model's. A
small MLP is given the simulator's exact state at the two context steps (the agent's and the T's
poses at ``t - 1`` and ``t``) and the two actions (targets) that a world model's window sees, all
in the T's own frame at ``t``, and predicts the T's pose at ``t + 1``. It trains on the world
model's training split and is scored on its ``test`` split (held-out episodes), by the T's IoU
between the predicted and the true pose (both drawn with ``goal_mask`` at the frames' size),
beside copying the pose at ``t``, split by how far the simulator's T moved (``probe.py``'s
groups: still, nudged, pushed), and by the T's IoU at the last step of a rollout over each test
episode in which it predicts the T from its own predictions (:func:`roll_out`; the agent and the
actions are the simulator's), beside copying the T of the last context step.

With ``--policies CONFIG`` it also rolls out the closed-loop simulator episodes of ``wmjax
eval-policy``'s default policies for that profile (:func:`policy_episodes`: its held-out start
states, 32 control steps): the episodes on whose last frame a policy evaluation scores the T
(``block_iou_push_end`` of ``run.py``'s summary), beside what the world model keeps there.

With ``--closed_loop`` (and ``--policies``) the learner is also run as a world model in those
policies' closed loop (:func:`closed_loop`): a second MLP predicts the agent, the predicted
state is drawn by the simulator's own renderer, the policy acts on those frames, and the T of
the last step is scored against the simulator's episode under the same policy and noise. That
is what goal 4 scores a world model on, for a learner of the same budget whose drawing is exact:
how much of the T a closed loop of this accuracy keeps.

With ``--perceived`` the inputs are read from the dataset's 48-pixel frames instead
(:func:`seen_states`: the agent's and the T's pixels, as ``wmjax.tasks.pusht.metrics`` reads
them): whether the frames a world model sees still hold what the state holds.

Two budgets: the world model's (``--wm_steps`` steps of ``--wm_batch``, as many transitions as its
training draws windows) and a long one (``--steps`` of ``--batch``), each at the learning rate
of ``--learning_rates`` with the least loss on the last tenth of the training episodes (held out
of the fit). If the MLP predicts the pushed T well within the world model's budget, the data
hold the contact dynamics and the world model does not read or draw them; if it does not even
with the long budget, two frames and the actions do not determine where the T goes, and no world
model of these inputs can draw it.

    python experiments/pusht/contact_from_state.py --data W/data/pusht/NAME/1.0.0 \\
        [--reference REF/pusht/NAME/1.0.0] [--policies configs/pusht.py:latent] [--perceived] \\
        --out C.json

Means and standard errors are over test episodes (each episode's transitions averaged first).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

MOTION_GROUPS = ((0.0, 0.5, "still"), (0.5, 5.0, "nudged"), (5.0, float("inf"), "pushed"))
POSITION_SCALE, TARGET_SCALE = 100.0, 10.0  # simulator units


def _rotate(points: np.ndarray, angle: np.ndarray) -> np.ndarray:
  """``points [N, ..., 2]`` rotated by ``angle [N]`` (radians)."""
  c, s = np.cos(angle), np.sin(angle)
  extra = (None,) * (points.ndim - 2)
  c, s = c[(slice(None),) + extra], s[(slice(None),) + extra]
  return np.stack([c * points[..., 0] - s * points[..., 1],
                   s * points[..., 0] + c * points[..., 1]], -1)


def features(agent_prev, agent_now, action_prev, action_now, block_prev, block_now) -> np.ndarray:
  """What a world model's window shows, in the T's frame at ``t``: the agent's positions at
  ``t - 1`` and ``t`` and the two actions ``[N, 2]`` each, and the T's poses at ``t - 1`` and ``t``
  ``[N, 3]`` -> ``inputs [N, 12]`` (those points less the T's position at ``t``, turned by minus
  its angle, in units of ``POSITION_SCALE``, and the sine and cosine of the T's turn)."""
  origin, angle = block_now[:, :2], block_now[:, 2]
  points = np.stack([agent_prev, agent_now, action_prev, action_now, block_prev[:, :2]], 1)
  local = _rotate(points - origin[:, None], -angle) / POSITION_SCALE
  turn = block_prev[:, 2] - angle
  return np.concatenate([local.reshape(len(points), -1),
                         np.stack([np.sin(turn), np.cos(turn)], 1)], 1).astype(np.float32)


def transitions(states: np.ndarray, actions: np.ndarray, seen: np.ndarray | None = None) -> dict:
  """Every ``(t - 1, t) -> t + 1`` transition of episodes ``states [E, T, 5]`` (agent x, y; T x,
  y, angle) and ``actions [E, T, 2]`` (``actions[t]`` leads from step ``t`` to ``t + 1``) ->
  ``inputs [N, 12]`` (:func:`features`, of the states ``seen``: by default the true ones) and
  ``targets [N, 3]`` (the true T's pose at ``t + 1`` in the seen T's frame at ``t``), and for
  scoring the seen poses ``now [N, 3]``, the true ``next [N, 3]``, how far the true T moves
  ``moved [N]`` (simulator units) and ``episode [N]``."""
  seen = states if seen is None else seen
  e, t = states.shape[:2]
  rows = [(i, j) for i in range(e) for j in range(1, t - 1)]
  ep, step = (np.asarray(v) for v in zip(*rows))
  s_prev, s_now, s_next = seen[ep, step - 1], seen[ep, step], states[ep, step + 1]
  inputs = features(s_prev[:, :2], s_now[:, :2], actions[ep, step - 1], actions[ep, step],
                    s_prev[:, 2:], s_now[:, 2:])
  origin, angle = s_now[:, 2:4], s_now[:, 4]
  move = _rotate((s_next[:, 2:4] - origin)[:, None], -angle)[:, 0] / TARGET_SCALE
  turn_next = np.angle(np.exp(1j * (s_next[:, 4] - angle)))
  targets = np.concatenate([move, 10.0 * turn_next[:, None]], 1)
  return {"inputs": inputs, "targets": targets.astype(np.float32),
          "now": s_now[:, 2:5].astype(np.float64), "next": s_next[:, 2:5].astype(np.float64),
          "moved": np.linalg.norm(s_next[:, 2:4] - states[ep, step, 2:4], axis=1), "episode": ep}


def agent_targets(states: np.ndarray, seen: np.ndarray | None = None) -> np.ndarray:
  """The agent's true position at ``t + 1`` in the seen T's frame at ``t``, in units of
  ``POSITION_SCALE``, for every transition of :func:`transitions` -> ``[N, 2]``."""
  seen = states if seen is None else seen
  e, t = states.shape[:2]
  ep, step = (np.asarray(v) for v in zip(*[(i, j) for i in range(e) for j in range(1, t - 1)]))
  now = seen[ep, step]
  local = _rotate((states[ep, step + 1, :2] - now[:, 2:4])[:, None], -now[:, 4])[:, 0]
  return (local / POSITION_SCALE).astype(np.float32)


def agent_from(targets: np.ndarray, now: np.ndarray) -> np.ndarray:
  """``targets [N, 2]`` (as :func:`agent_targets` writes them) and the T's poses at ``t`` ->
  the agent's world positions ``[N, 2]``."""
  return now[:, :2] + _rotate(targets[:, None] * POSITION_SCALE, now[:, 2])[:, 0]


def predicted_state(predict, predict_agent, prev: np.ndarray, now: np.ndarray,
                    action_prev: np.ndarray, action_now: np.ndarray) -> np.ndarray:
  """The learner's next state ``[N, 5]`` from the states ``prev`` and ``now [N, 5]`` and the two
  actions ``[N, 2]``: the T's pose from ``predict``, the agent's position from
  ``predict_agent``."""
  inputs = features(prev[:, :2], now[:, :2], action_prev, action_now, prev[:, 2:], now[:, 2:])
  return np.concatenate([agent_from(predict_agent(inputs), now[:, 2:]),
                         poses_from(predict(inputs), now[:, 2:])], 1)


def draw_states(renderer, states: np.ndarray) -> np.ndarray:
  """``states [N, 5]`` drawn by the simulator's own renderer (a :class:`PushTSimulator` of ``N``
  environments, reset to them) -> frames ``[N, S, S, 3]`` uint8."""
  from wmjax.tasks.pusht.simulator import reset_state
  return renderer.reset(np.stack([reset_state(s[:2], s[2:4], s[4]) for s in states]))[0]


def closed_loop(predict, predict_agent, policy, states: np.ndarray, actions: np.ndarray,
                steps: int, key, *, image_size: int, action_repeat: int,
                perceived: bool = False) -> np.ndarray:
  """``policy`` run closed loop in the learned model from the first two steps of ``states [E,
  T, 5]`` and the action between them: the T's next pose from ``predict``, the agent's from
  ``predict_agent``, each step's predicted state drawn by the simulator's renderer
  (:class:`PushTSimulator` reset to it) and shown to the policy, which is called as
  :func:`wmjax.tasks.pusht.simulator.simulate_policy` calls it (the same keys). With
  ``perceived`` the learner's inputs are read back off those frames (:func:`seen_states`), as a
  world model's are off its own. Returns the predicted states ``[E, 2 + steps, 5]``."""
  import jax

  from wmjax.frames import to_model
  from wmjax.tasks.pusht.simulator import PushTSimulator

  renderer = PushTSimulator(len(states), image_size, action_repeat)
  predicted = [states[:, 0], states[:, 1]]
  frames = [draw_states(renderer, predicted[0]), draw_states(renderer, predicted[1])]
  seen = ([seen_states(f[:, None])[:, 0] for f in frames] if perceived else list(predicted))
  taken = [actions[:, 0]]
  chunk, call = np.zeros((len(states), 0, 2)), 0
  for _ in range(steps):
    if chunk.shape[1] == 0:
      chunk = np.asarray(policy(to_model(np.stack(frames[-2:], 1)), jax.random.fold_in(key, call)))
      call += 1
    taken.append(chunk[:, 0].astype(np.float64))
    chunk = chunk[:, 1:]
    predicted.append(predicted_state(predict, predict_agent, seen[-2], seen[-1], taken[-2],
                                     taken[-1]))
    frames.append(draw_states(renderer, predicted[-1]))
    seen.append(seen_states(frames[-1][:, None])[:, 0] if perceived else predicted[-1])
  return np.stack(predicted, 1)


def roll_out(predict, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
  """The T's poses ``[E, T - 2, 3]`` at steps ``2 .. T - 1`` of episodes ``states [E, T, 5]``
  (true or seen), each predicted from the predictions before it (the T at steps 0 and 1 and the
  agent and the actions at every step are the given ones): how far one-step errors carry over
  a rollout."""
  blocks = [states[:, 0, 2:], states[:, 1, 2:]]
  for t in range(1, states.shape[1] - 1):
    inputs = features(states[:, t - 1, :2], states[:, t, :2], actions[:, t - 1], actions[:, t],
                      blocks[-2], blocks[-1])
    blocks.append(poses_from(predict(inputs), blocks[-1]))
  return np.stack(blocks[2:], 1)


def poses_from(targets: np.ndarray, now: np.ndarray) -> np.ndarray:
  """``targets [N, 3]`` (as :func:`transitions` writes them) and the poses at ``t`` -> the world
  poses ``[N, 3]`` they stand for."""
  move = _rotate(targets[:, None, :2] * TARGET_SCALE, now[:, 2])[:, 0]
  return np.concatenate([now[:, :2] + move, (now[:, 2] + targets[:, 2] / 10.0)[:, None]], 1)


def block_iou(first: np.ndarray, second: np.ndarray, size: int) -> np.ndarray:
  """The T's IoU between poses ``first [N, 3]`` and ``second [N, 3]`` drawn at ``size``."""
  from wmjax.tasks.pusht.simulator import goal_mask
  out = np.empty(len(first))
  for i, (a, b) in enumerate(zip(first, second)):
    ma, mb = goal_mask(size, a), goal_mask(size, b)
    out[i] = (ma & mb).sum() / max((ma | mb).sum(), 1)
  return out


def fit(inputs: np.ndarray, targets: np.ndarray, steps: int, batch: int, seed: int,
        width: int = 256, depth: int = 3, learning_rate: float = 1e-3):
  """An MLP ``inputs [N, 12] -> targets [N, 3]`` fitted by Adam on the MSE of standardised
  targets -> a function ``inputs -> targets``."""
  import flax.linen as nn
  import jax
  import jax.numpy as jnp
  import optax

  mean, std = targets.mean(0), targets.std(0) + 1e-6

  class MLP(nn.Module):
    @nn.compact
    def __call__(self, x):
      for _ in range(depth):
        x = nn.gelu(nn.Dense(width)(x))
      return nn.Dense(targets.shape[1])(x)

  net = MLP()
  params = net.init(jax.random.key(seed), inputs[:1])
  optimizer = optax.adamw(optax.cosine_decay_schedule(learning_rate, steps), weight_decay=1e-4)
  state = optimizer.init(params)
  x_all, y_all = jnp.asarray(inputs), jnp.asarray((targets - mean) / std)

  @jax.jit
  def step(params, state, key):
    index = jax.random.randint(key, (batch,), 0, len(x_all))

    def loss(p):
      return jnp.mean((net.apply(p, x_all[index]) - y_all[index]) ** 2)

    value, grads = jax.value_and_grad(loss)(params)
    updates, state = optimizer.update(grads, state, params)
    return optax.apply_updates(params, updates), state, value

  key = jax.random.key(seed + 1)
  for i in range(steps):
    params, state, _ = step(params, state, jax.random.fold_in(key, i))
  apply = jax.jit(net.apply)
  return lambda x: np.asarray(apply(params, jnp.asarray(x))) * std + mean


def fit_selected(train: dict, validation: dict, steps: int, batch: int, seed: int,
                 learning_rates: str = "1e-3,3e-3,1e-2", **network):
  """:func:`fit` (``network``: its ``width`` and ``depth``) at each of the comma-separated
  ``learning_rates`` on ``train`` (as :func:`transitions` writes it) -> ``(predict, learning
  rate, validation MSE per rate)`` of the rate with the least MSE on ``validation``."""
  losses, fitted = {}, {}
  for rate in (float(r) for r in learning_rates.split(",")):
    fitted[rate] = fit(train["inputs"], train["targets"], steps, batch, seed, learning_rate=rate,
                       **network)
    losses[rate] = float(np.mean((fitted[rate](validation["inputs"]) - validation["targets"]) ** 2))
  rate = min(losses, key=losses.get)
  return fitted[rate], rate, losses


def _mean_se(values: np.ndarray, episodes: np.ndarray) -> dict:
  """Mean and standard error over episodes of ``values [N]``, each episode's values averaged
  first."""
  from wmjax.eval.metrics import mean_stderr

  ids = np.unique(episodes)
  mean, stderr = mean_stderr([values[episodes == e].mean() for e in ids])
  return {"mean": float(mean), "stderr": float(stderr), "episodes": int(len(ids)),
          "transitions": int(len(values))}


def score(predicted: np.ndarray, data: dict, size: int) -> dict:
  """T IoU, centre error (simulator units) and angle error (degrees) of ``predicted [N, 3]``
  poses against the true next poses, per group of the true T's motion."""
  moved = data["moved"]
  iou = block_iou(predicted, data["next"], size)
  centre = np.linalg.norm(predicted[:, :2] - data["next"][:, :2], axis=1)
  angle = np.abs(np.degrees(np.angle(np.exp(1j * (predicted[:, 2] - data["next"][:, 2])))))
  out = {}
  for lo, hi, name in MOTION_GROUPS:
    keep = (moved >= lo) & (moved < hi)
    if keep.any():
      out[name] = {key: _mean_se(v[keep], data["episode"][keep])
                   for key, v in (("block_iou", iou), ("centre_error", centre),
                                  ("angle_error_deg", angle))}
  return out


def rollout_end(predicted: np.ndarray, states: np.ndarray, size: int) -> dict:
  """T IoU of the last step's ``predicted [E, 3]`` poses against ``states [E, T, 5]``'s, over all
  episodes and over those whose T moved 5 units or more between step 1 and the last."""
  iou = block_iou(predicted, states[:, -1, 2:], size)
  moved = np.linalg.norm(states[:, -1, 2:4] - states[:, 1, 2:4], axis=1) >= 5.0
  episodes = np.arange(len(states))
  return {"all": _mean_se(iou, episodes), "moved": _mean_se(iou[moved], episodes[moved])}


def seen_states(frames: np.ndarray) -> np.ndarray:
  """What the frames ``[E, T, H, W, 3]`` uint8 show of the state -> ``[E, T, 5]``: the agent's
  and the T's centroids of their pixels (world units) and the T's angle from its pixels
  (:func:`wmjax.tasks.pusht.metrics.block_pose`), the T's position moved from its centre of
  area to its body origin as the simulator keeps it."""
  from wmjax.frames import to_model
  from wmjax.tasks.pusht.metrics import block_pose
  from wmjax.tasks.pusht.simulator import T_CENTROID, centroids, object_masks

  flat = to_model(frames.reshape((-1,) + frames.shape[2:]))
  block_xy, agent_xy, _ = (np.asarray(v, np.float64) for v in centroids(flat))
  _, angle, _ = block_pose(np.asarray(object_masks(flat)[0]))
  origin = block_xy - _rotate(np.asarray(T_CENTROID)[None, None], angle)[:, 0]
  return np.concatenate([agent_xy, origin, angle[:, None]], 1).reshape(frames.shape[:2] + (5,))


def _profile_policies(config_file: str) -> tuple:
  """``(config, its Push-T data parameters, eval-policy's default policies by name)`` of the
  profile ``config_file``."""
  from wmjax.config import load_config
  from wmjax.tasks.pusht import evaluate
  from wmjax.tasks.pusht.dataset import PushTConfig

  config = load_config(config_file)
  return (config, PushTConfig.from_dict(config.data.pusht),
          evaluate.policies_from_specs(None, evaluate.policy_chunk(config)))


def policy_episodes(config_file: str, episodes: int, control_steps: int = 32,
                    frames: bool = False) -> dict[str, tuple[np.ndarray, ...]]:
  """Per policy of ``wmjax eval-policy``'s default set, ``states [E, T, 5]`` and ``actions [E,
  T, 2]`` of its ``episodes`` closed-loop simulator episodes of ``control_steps`` control steps,
  from the held-out start states and with the policy noise that ``eval-policy`` draws for the
  profile ``config_file`` (its ``--seed 0``; :func:`wmjax.tasks.pusht.evaluate.evaluate_policies`),
  and with ``frames`` the states its frames show: the episodes on whose last frame a policy
  evaluation scores the T."""
  import jax

  from wmjax.tasks.pusht import evaluate
  from wmjax.tasks.pusht.simulator import simulate_policy

  config, params, policies = _profile_policies(config_file)
  states = evaluate.initial_states(config, episodes, "evaluate")
  if not evaluate.held_out(config, states):
    raise ValueError(f"the evaluation start states of {config_file} meet its training split")
  out = {}
  for index, (name, policy) in enumerate(policies.items()):
    truth = simulate_policy(policy, states, params.actions_for(control_steps),
                            image_size=params.image_size,
                            key=jax.random.fold_in(jax.random.key(0), index),
                            context=config.rollout.context, action_repeat=params.action_repeat)
    out[name] = (truth["state"].astype(np.float64), truth["actions"].astype(np.float64))
    if frames:
      out[name] += (seen_states(truth["frames"]),)
  return out


def policy_closed_loops(config_file: str, predict, predict_agent,
                        truth: dict[str, tuple[np.ndarray, ...]], size: int,
                        control_steps: int = 32, perceived: bool = False) -> dict[str, dict]:
  """Per policy of :func:`policy_episodes`, the learner run closed loop (:func:`closed_loop`)
  from its episodes' first two steps with the same policy noise, scored at the last step against
  the simulator's episode ``truth[name]``: the T's IoU (:func:`rollout_end`) and the agent's
  error (simulator units)."""
  import jax

  _, params, policies = _profile_policies(config_file)
  out = {}
  for index, (name, policy) in enumerate(policies.items()):
    states, actions = truth[name][:2]
    predicted = closed_loop(predict, predict_agent, policy, states[:, :2], actions,
                            params.actions_for(control_steps),
                            jax.random.fold_in(jax.random.key(0), index),
                            image_size=params.image_size, action_repeat=params.action_repeat,
                            perceived=perceived)
    agent_error = np.linalg.norm(predicted[:, -1, :2] - states[:, -1, :2], axis=1)
    out[name] = {**rollout_end(predicted[:, -1, 2:], states, size),
                 "agent_error_end": _mean_se(agent_error, np.arange(len(states)))}
  return out


def read_split(data_dir: str, split: str, frames: bool = False) -> tuple[np.ndarray, ...]:
  """``states [E, T, 5]`` and ``actions [E, T, 2]`` of a Push-T dataset's split, and with
  ``frames`` the states its frames show (:func:`seen_states`)."""
  import wmjax.tasks.pusht  # noqa: F401  (registers the Push-T spec)
  from wmjax.data.rlds import decode_image
  from wmjax.data.sources import ArrayRecordEpisodes

  source = ArrayRecordEpisodes(data_dir, split, "pusht")
  episodes = [source.episode(i) for i in range(len(source))]
  out = (np.stack([e.extras["state"] for e in episodes]).astype(np.float64),
         np.stack([e.actions for e in episodes]).astype(np.float64))
  if not frames:
    return out
  images = np.stack([[decode_image(image, None) for image in e.images] for e in episodes])
  return out + (seen_states(images),)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--data", required=True, help="the Push-T builder directory (…/1.0.0)")
  parser.add_argument("--reference", help="another Push-T builder directory whose test episodes "
                      "are rolled out too (e.g. probe.py's all-scripted reference data)")
  parser.add_argument("--policies", metavar="CONFIG",
                      help="also roll out the episodes of `wmjax eval-policy`'s default policies "
                           "for this config (e.g. configs/pusht.py:latent, whose data --data "
                           "is): held-out start states, 32 control steps (policy_episodes)")
  parser.add_argument("--closed_loop", action="store_true",
                      help="with --policies: also run the learner closed loop in those policies' "
                           "episodes, its states drawn by the simulator's renderer (closed_loop)")
  parser.add_argument("--agent_budget", choices=("same", "long"), default="same",
                      help="the closed loop's agent MLP trained at each budget's own steps and "
                           "batch (same), or always at the long one's (long): how much of what "
                           "the closed loop loses is the agent's")
  parser.add_argument("--policy_episodes", type=int, default=48, help="episodes per policy")
  parser.add_argument("--size", type=int, default=48, help="frame size the T is drawn at")
  parser.add_argument("--wm_steps", type=int, default=3000)
  parser.add_argument("--wm_batch", type=int, default=16)
  parser.add_argument("--steps", type=int, default=10000)
  parser.add_argument("--batch", type=int, default=256)
  parser.add_argument("--learning_rates", default="1e-3,3e-3,1e-2",
                      help="tried at each budget; the one with the least validation loss (the "
                           "last tenth of the training episodes, not trained on) is scored")
  parser.add_argument("--width", type=int, default=256, help="the MLPs' hidden width")
  parser.add_argument("--depth", type=int, default=3, help="the MLPs' hidden layers")
  parser.add_argument("--perceived", action="store_true",
                      help="the MLP's inputs read from the dataset's frames (seen_states) instead "
                           "of the simulator's state; the targets stay the true poses")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--out", required=True, help="JSON file for every number")
  args = parser.parse_args(argv)
  if args.closed_loop and not args.policies:
    parser.error("--closed_loop needs --policies CONFIG")

  def inputs_from(read):  # (true states, actions, the states the inputs are read from)
    return read if args.perceived else read + (read[0],)

  def episodes(data_dir, split):
    return inputs_from(read_split(data_dir, split, frames=args.perceived))

  train_split = episodes(args.data, "train")
  keep = len(train_split[0]) - len(train_split[0]) // 10
  train = transitions(*(v[:keep] for v in train_split))
  validation = transitions(*(v[keep:] for v in train_split))
  splits = {"test": episodes(args.data, "test")}
  if args.reference:
    splits["reference"] = episodes(args.reference, "test")
  if args.policies:
    truth_episodes = policy_episodes(args.policies, args.policy_episodes, frames=args.perceived)
    for name, read in truth_episodes.items():
      splits[f"policy_{name}"] = inputs_from(read)
  test, truth = transitions(*splits["test"]), transitions(*splits["test"][:2])
  result = {"data": args.data, "reference": args.reference, "seed": args.seed,
            "agent_budget": args.agent_budget, "width": args.width, "depth": args.depth,
            "inputs": "read from the frames" if args.perceived else "the simulator's state",
            "train_transitions": len(train["inputs"]),
            "validation_transitions": len(validation["inputs"]),
            "test_transitions": len(test["inputs"]),
            "copy": {"test": score(truth["now"], truth, args.size),
                     **{f"{split}_rollout_end": rollout_end(s[:, 1, 2:], s, args.size)
                        for split, (s, _, _) in splits.items()}}}
  for name, steps, batch in (("world_model_budget", args.wm_steps, args.wm_batch),
                             ("long", args.steps, args.batch)):
    network = dict(width=args.width, depth=args.depth)
    predict, rate, losses = fit_selected(train, validation, steps, batch, args.seed,
                                         args.learning_rates, **network)
    loops = {}
    if args.closed_loop:
      agent_steps, agent_batch = ((args.steps, args.batch) if args.agent_budget == "long"
                                  else (steps, batch))
      predict_agent = fit(train["inputs"], agent_targets(*(v[:keep] for v in train_split[::2])),
                          agent_steps, agent_batch, args.seed, learning_rate=rate, **network)
      loops = {"closed_loop": policy_closed_loops(args.policies, predict, predict_agent,
                                                  truth_episodes, args.size,
                                                  perceived=args.perceived)}
    result[name] = {**loops, "steps": steps, "batch": batch, "learning_rate": rate,
                    "validation_mse": {f"{r:g}": v for r, v in losses.items()},
                    "test": score(poses_from(predict(test["inputs"]), test["now"]), test, args.size),
                    **{f"{split}_rollout_end": rollout_end(roll_out(predict, seen, a)[:, -1],
                                                           s, args.size)
                       for split, (s, a, seen) in splits.items()}}
  for name in ("copy", "world_model_budget", "long"):
    print(name, "one step", json.dumps({g: v["block_iou"] for g, v in result[name]["test"].items()}))
    for key in (k for k in result[name] if k.endswith("rollout_end")):
      print(name, key, json.dumps(result[name][key]))
    for policy, value in result[name].get("closed_loop", {}).items():
      print(name, "closed loop", policy, json.dumps(value))
  with open(args.out, "w") as f:
    json.dump(result, f, indent=1)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
