"""Planning by ranking: the best-scored candidate is executed, candidates are imagined in order,
proposals have the documented shapes, and the closed loop replans until the steps are done."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import tiny_world_model
from wmjax.eval import planning
from wmjax.rollout import rollout

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def model():
  return tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                          "model.action_dim=2", frame_shape=(8, 8, 3))


def line_policy(frames, key):
  """Random straight chunks of 3 actions."""
  direction = jax.random.normal(key, (frames.shape[0], 1, 2))
  return direction * jnp.arange(1, 4, dtype=jnp.float32)[:, None]


def test_the_best_scored_candidate_is_chosen(model):
  wm, params = model
  scores = np.array([[0.1, 0.9, 0.3, -1.0], [np.nan, 0.2, 0.7, 0.1]])
  seen = {}

  def value(frames, instruction):
    seen["frames"], seen["instruction"] = frames, instruction
    return scores.reshape(-1)

  planner = planning.Planner(wm, params, planning.policy_proposal(line_policy), value,
                             num_candidates=4, horizon=3, instruction=["a", "b"])
  frames = jax.random.uniform(jax.random.key(0), (2, 1, 8, 8, 3), minval=-1, maxval=1)
  plan = planner.plan(frames, None, jax.random.key(1))
  np.testing.assert_array_equal(plan.index, [1, 2])
  np.testing.assert_array_equal(plan.best, plan.candidates[[0, 1], [1, 2]])
  assert seen["frames"].shape == (8, 4, 8, 8, 3) and seen["instruction"] == ["a"] * 4 + ["b"] * 4
  # the candidates are distinct samples of the policy
  assert np.abs(plan.candidates[:, 0] - plan.candidates[:, 1]).max() > 1e-3


def test_imagined_candidates_are_their_own_rollouts(model):
  wm, params = model
  planner = planning.Planner(wm, params, planning.policy_proposal(line_policy),
                             lambda f, i: np.zeros(len(f)), num_candidates=3, horizon=3)
  frames = jax.random.uniform(jax.random.key(2), (2, 1, 8, 8, 3), minval=-1, maxval=1)
  candidates = np.asarray(jax.random.normal(jax.random.key(3), (2, 3, 3, 2)))
  rng = jax.random.key(4)
  imagined = planner.imagine(frames, None, candidates, rng)
  assert imagined.shape == (2, 3, 4, 8, 8, 3)
  # same as rolling out the flattened batch directly, candidate (1, 2) at row 1 * 3 + 2
  direct = rollout(wm, params, jnp.repeat(frames, 3, 0), candidates.reshape(6, 3, 2),
                   jax.random.split(rng)[1], horizon=3)
  np.testing.assert_allclose(imagined[1, 2], direct[5], atol=1e-5)
  # a different chunk imagines a different future
  assert np.abs(imagined[1, 2, -1] - imagined[1, 0, -1]).max() > 1e-4


def test_one_candidate_is_the_proposal_itself(model):
  wm, params = model

  def value(frames, instruction):
    raise AssertionError("nothing is imagined with K = 1")

  planner = planning.Planner(wm, params, planning.policy_proposal(line_policy), value,
                             num_candidates=1, horizon=3)
  plan = planner.plan(np.zeros((2, 1, 8, 8, 3), np.float32), None, jax.random.key(0))
  assert plan.best.shape == (2, 3, 2) and plan.imagined is None and np.isnan(plan.scores).all()


def test_sphere_proposal_paths_end_on_the_sphere():
  start = np.array([[10.0, 20.0], [100.0, 50.0]])
  propose = planning.sphere_proposal(lambda frame: start, radius=5.0, length=4)
  paths = np.asarray(propose(np.zeros((2, 1, 8, 8, 3)), jax.random.key(0), 7))
  assert paths.shape == (2, 7, 4, 2)
  np.testing.assert_allclose(np.linalg.norm(paths[:, :, -1] - start[:, None], axis=-1), 5.0,
                             rtol=1e-5)
  np.testing.assert_allclose(paths[:, :, 1] - start[:, None], (paths[:, :, -1] - start[:, None])
                             / 2, atol=1e-5)


def test_closed_loop_executes_the_chosen_actions_and_replans(model):
  wm, params = model
  executed = []

  def step_fn(action):
    executed.append(action)
    return np.full((2, 8, 8, 3), len(executed) / 10, np.float32)

  # value: prefer the candidate whose imagined last frame is brightest
  planner = planning.Planner(wm, params, planning.policy_proposal(line_policy),
                             lambda f, i: f[:, -1].mean((1, 2, 3)), num_candidates=3, horizon=3)
  out = planning.run_closed_loop(planner, step_fn, np.zeros((2, 2, 8, 8, 3), np.float32), 7,
                                 jax.random.key(5), context_actions=np.zeros((2, 1, 2)),
                                 execute=2)
  assert out["frames"].shape == (2, 9, 8, 8, 3) and out["actions"].shape == (2, 7, 2)
  assert len(out["plans"]) == 4  # 2 + 2 + 2 + 1 actions
  np.testing.assert_allclose(out["actions"][:, :2], out["plans"][0].best[:, :2])
  np.testing.assert_allclose(np.stack(executed, 1), out["actions"])
  for plan in out["plans"]:
    np.testing.assert_array_equal(plan.index, np.nanargmax(plan.scores, 1))
