"""Policy evaluation: Monte Carlo values in a toy deterministic world whose values are known, the
closed-loop scan equal to the environment loop, and the agreement scores."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import tiny_world_model
from wmjax.data.stats import ActionStats
from wmjax.env import WorldModelEnv
from wmjax.eval import policy_eval

pytestmark = pytest.mark.unit


class ToyWorld:
  """A deterministic stand-in for WorldModelEnv: a white pixel on an 8x8 frame moves by the
  (rounded, clipped) 2-D action; the goal is the bottom-right corner."""

  context, horizon, action_dim, size = 1, 2, 2, 8

  def reset(self, initial_frames, instruction=None, context_actions=None):
    self._frames = [np.asarray(initial_frames, np.float32)]
    return self._frames[0], {}

  @property
  def num_envs(self):
    return self._frames[0].shape[0]

  def video(self):
    return np.concatenate(self._frames, 1)

  def step(self, chunk):
    for action in np.moveaxis(np.asarray(chunk), 1, 0):
      position = np.clip(pixel_position(self._frames[-1][:, -1]) + np.round(action), 0, 7)
      self._frames.append(render(position.astype(int))[:, None])
    return self._frames[-1], None, None, None, {}


def render(positions):
  frames = -np.ones((len(positions), 8, 8, 3), np.float32)
  frames[np.arange(len(positions)), positions[:, 0], positions[:, 1]] = 1.0
  return frames


def pixel_position(frames):
  flat = np.asarray(frames).mean(-1).reshape(len(frames), -1).argmax(-1)
  return np.stack([flat // 8, flat % 8], -1).astype(np.float32)


def reached_goal(frames, instruction):
  del instruction
  return (pixel_position(np.asarray(frames)[:, -1]) == 7).all(-1).astype(np.float32)


def go_to_goal(frames, key):
  del key
  return np.ones((len(frames), 2, 2), np.float32)


def stay(frames, key):
  del key
  return np.zeros((len(frames), 2, 2), np.float32)


def every_other_stays(frames, key):
  """Goes to the goal in the even-numbered environments only: value exactly 1/2."""
  del key
  out = go_to_goal(frames, None)
  out[1::2] = 0.0
  return out


def test_monte_carlo_values_of_policies_with_known_success():
  world = ToyWorld()
  start = render(np.zeros((8, 2), int))[:, None]  # 8 episodes from the top-left corner
  values = {}
  for name, policy in [("goal", go_to_goal), ("half", every_other_stays), ("stay", stay)]:
    episode = policy_eval.env_episodes(world, policy, start, steps=8, key=jax.random.key(0))
    assert episode["frames"].shape == (8, 9, 8, 8, 3) and episode["actions"].shape == (8, 8, 2)
    values[name] = policy_eval.policy_value(
        policy_eval.episode_returns(episode["frames"], reached_goal))
  assert values["goal"].mean == 1.0 and values["goal"].stderr == 0.0
  assert values["half"].mean == 0.5 and values["half"].stderr == pytest.approx(
      np.std([1, 0] * 4, ddof=1) / np.sqrt(8))
  assert values["stay"].mean == 0.0
  # 6 steps of one pixel do not reach (7, 7) from (0, 0): horizon matters
  short = policy_eval.env_episodes(world, go_to_goal, start, steps=6, key=jax.random.key(0))
  assert policy_eval.episode_returns(short["frames"], reached_goal).sum() == 0


def test_agreement_scores():
  perfect = policy_eval.agreement([0.9, 0.5, 0.2, 0.1], [0.7, 0.45, 0.3, 0.05])
  assert perfect["ranking_preserved"] == 1.0 and perfect["kendall"] == pytest.approx(1.0)
  assert perfect["pairwise_rank_agreement"] == 1.0 and perfect["mmrv"] == 0.0
  assert perfect["value_gap"] == pytest.approx((0.2 + 0.05 + 0.1 + 0.05) / 4)
  swapped = policy_eval.agreement([0.9, 0.5, 0.2, 0.1], [0.7, 0.2, 0.3, 0.05])
  assert swapped["ranking_preserved"] == 0.0 and swapped["top1"] == 1.0
  assert swapped["pairwise_rank_agreement"] == pytest.approx(5 / 6)
  assert swapped["mmrv"] == pytest.approx((0.3 + 0.3) / 4)  # policies 1 and 2 inverted, gap 0.3
  np.testing.assert_allclose(swapped["pearson"], np.corrcoef([0.9, 0.5, 0.2, 0.1],
                                                             [0.7, 0.2, 0.3, 0.05])[0, 1])
  tied = policy_eval.agreement([0.5, 0.5, 0.5], [0.1, 0.2, 0.3])
  assert np.isnan(tied["pearson"]) and np.isnan(tied["ranking_preserved"])
  with pytest.raises(ValueError, match="P >= 3"):
    policy_eval.agreement([1.0, 0.0], [1.0, 0.0])
  with pytest.raises(ValueError, match="no finite return"):
    policy_eval.policy_value([np.nan, np.nan])


def test_agreement_intervals_resample_episodes_within_policy():
  """Well separated policies whose estimates follow the truth episode by episode: a narrow
  interval near 1 that holds the point estimate. Policies whose values lie within noise of each
  other: a wide one. Estimates paired with the truth per episode: resampling keeps the pairs."""
  rng = np.random.default_rng(0)
  means = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
  true = [m + 0.05 * rng.standard_normal(48) for m in means]
  estimated = [0.8 * t + 0.01 * rng.standard_normal(48) for t in true]
  clear = policy_eval.agreement_intervals(true, estimated, samples=500)
  point = policy_eval.agreement([t.mean() for t in true], [e.mean() for e in estimated])
  assert 0.99 < clear["pearson"][0] <= point["pearson"] <= clear["pearson"][1] <= 1.0
  assert clear["spearman"] == [1.0, 1.0] and clear["undefined_pearson"] == 0
  noisy_true = [0.5 + 0.3 * rng.standard_normal(12) for _ in range(5)]
  noisy = policy_eval.agreement_intervals(noisy_true, [rng.standard_normal(12) for _ in range(5)],
                                          samples=500)
  assert noisy["pearson"][1] - noisy["pearson"][0] > 1.0
  assert noisy["spearman"][0] < 0 < noisy["spearman"][1]
  # the same draws for the same seed; NaN returns are left out as in policy_value
  again = policy_eval.agreement_intervals(true, estimated, samples=500)
  assert again == clear
  with_nan = [np.append(e, np.nan) for e in estimated]
  assert policy_eval.agreement_intervals([np.append(t, 0.5) for t in true], with_nan,
                                         samples=100)["pearson"][0] > 0.9
  constant = policy_eval.agreement_intervals([np.ones(4)] * 3, [np.arange(4.0)] * 3, samples=50)
  assert constant["pearson"] is None and constant["undefined_pearson"] == 50
  with pytest.raises(ValueError, match="paired"):
    policy_eval.agreement_intervals([np.ones(4)] * 3, [np.ones(4), np.ones(3), np.ones(4)])
  with pytest.raises(ValueError, match="P >= 3"):
    policy_eval.agreement_intervals([np.ones(4)] * 2, [np.ones(4)] * 2)


def brightness_policy(frames, key):
  """A pure-JAX policy: the mean brightness of the newest frame, plus noise."""
  mean = jnp.asarray(frames)[:, -1].mean((1, 2, 3))
  actions = jnp.stack([mean * 4.0 + 3.0, -mean * 2.0], -1)[:, None].repeat(3, 1)
  return actions + jax.random.normal(key, actions.shape)


@pytest.mark.slow
@pytest.mark.parametrize("context,batch,horizon", [(1, 2, 3), (2, 8, 2)])
def test_scan_equals_the_environment_loop(context, batch, horizon):
  """B = 8 runs split over the 8 test devices; B = 2 does not divide and stays on one. The
  policy's chunks of 3 run in one block of 3, or in blocks of 2 and 1 (horizon 2): the policy is
  called once per chunk either way."""
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                                "model.action_dim=2", frame_shape=(8, 8, 3))
  stats = ActionStats.compute(np.random.default_rng(0).normal(3.0, 2.0, (100, 2)), "toy", None)
  start = jax.random.uniform(jax.random.key(3), (batch, context, 8, 8, 3), minval=-1, maxval=1)
  context_actions = np.full((batch, context - 1, 2), 3.0, np.float32)
  rng, key = jax.random.key(5), jax.random.key(6)
  calls = []

  def counted(frames, k):
    calls.append(k)
    return brightness_policy(frames, k)

  env = WorldModelEnv(wm, params, context=context, horizon=horizon, action_stats=stats, seed=rng)
  looped = policy_eval.env_episodes(env, counted, start, steps=5, key=key,
                                    context_actions=context_actions)
  assert len(calls) == 2 and looped["frames"].shape[1] == context + 5
  scanned = policy_eval.scan_episodes(wm, params, brightness_policy, start, 5, rng, key,
                                      horizon=horizon, action_stats=stats,
                                      context_actions=context_actions)
  assert len(scanned["frames"].sharding.device_set) == (8 if batch == 8 else 1)
  np.testing.assert_allclose(scanned["actions"], looped["actions"], rtol=1e-5, atol=1e-5)
  # float32 rounding of differently fused programs, amplified by the random eps-model: a few
  # pixels of 12288 differ by up to 5e-4 at B = 8
  np.testing.assert_allclose(scanned["frames"], looped["frames"], rtol=1e-3, atol=1e-3)
  with pytest.raises(ValueError, match="k>=1, A=2"):
    policy_eval.scan_episodes(wm, params, lambda f, k: brightness_policy(f, k)[..., :1], start,
                              2, rng, key, horizon=horizon, action_stats=stats,
                              context_actions=context_actions)


def test_scan_takes_device_frames_inside_jit():
  """uint8 jnp frames, traced inside an outer jit, split over the 8 devices (B = 8) or not."""
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                                "model.action_dim=2", frame_shape=(8, 8, 3))
  rng, key = jax.random.key(5), jax.random.key(6)

  def frames(start):
    return policy_eval.scan_episodes(wm, params, brightness_policy, start, 3, rng, key,
                                     horizon=3)["frames"]

  for batch in (2, 8):
    start = jax.random.randint(jax.random.key(batch), (batch, 1, 8, 8, 3), 0, 256, jnp.uint8)
    np.testing.assert_allclose(jax.jit(frames)(start), frames(np.asarray(start)), atol=1e-3)
