"""Schedules, targets, samplers and scheduling matrices against the papers' formulas."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wmjax.diffusion import (FlowMatching, GaussianDiffusion, LevelSampling, SamplerConfig,
                             classifier_free_guidance, context_inputs, ddim_step, diffusion_loss,
                             make_betas, masked_loss_sum, sample_window, scheduling_matrix,
                             training_levels, window_denoiser)
from wmjax.diffusion.objectives import object_weights
from wmjax.diffusion import schedules

pytestmark = pytest.mark.unit

SHAPE = (2, 5, 4, 4, 3)  # [B, T, H, W, C]


def _sig(z):
  return 1 / (1 + np.exp(-z))


def test_sigmoid_schedule_matches_wpe():
  abar = schedules.alphas_cumprod(make_betas("sigmoid"))
  assert abar.shape == (1000,)
  assert abar[499] == pytest.approx(0.5, abs=1e-3)
  # Level 999 is level 998 times the clipped beta 0.999 of the last step.
  u = 999 / 1000
  expected_998 = (_sig(3) - _sig(6 * u - 3)) / (_sig(3) - _sig(-3))
  assert abar[998] == pytest.approx(expected_998, rel=1e-6)
  assert abar[999] == pytest.approx(expected_998 * 1e-3, rel=1e-6)
  assert 1e-7 < abar[999] < 5e-7
  assert np.all(np.diff(abar) < 0)


def test_linear_and_cosine_schedules():
  betas = make_betas("linear")
  assert betas[0] == pytest.approx(1e-4) and betas[-1] == pytest.approx(0.02)
  abar = schedules.alphas_cumprod(betas)
  assert abar[999] == pytest.approx(4.036e-5, rel=1e-3)  # the DDPM / DiT value
  cosine = schedules.alphas_cumprod(make_betas("cosine"))
  s = 0.008
  f = lambda u: np.cos((u + s) / (1 + s) * np.pi / 2) ** 2
  assert cosine[499] == pytest.approx(f(0.5) / f(0.0), rel=1e-6)
  assert make_betas("cosine").max() == pytest.approx(0.999)
  with pytest.raises(ValueError, match="noise schedule must be one of"):
    make_betas("quadratic")


def _random_case(seed=0, flow=False):
  k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
  x0 = jax.random.normal(k1, SHAPE)
  eps = jax.random.normal(k2, SHAPE)
  if flow:
    levels = jax.random.uniform(k3, SHAPE[:2], minval=0.01, maxval=1.0)
  else:
    levels = jax.random.randint(k3, SHAPE[:2], 0, 1000)
  return x0, eps, levels


@pytest.mark.parametrize("prediction", ["eps", "v", "x0"])
@pytest.mark.parametrize("schedule", ["linear", "sigmoid"])
def test_target_round_trip(prediction, schedule):
  process = GaussianDiffusion.create(schedule, prediction=prediction)
  x0, eps, levels = _random_case()
  x_t = process.add_noise(x0, levels, eps)
  ab = process.abar(levels)[:, :, None, None, None]
  np.testing.assert_allclose(x_t, np.sqrt(ab) * x0 + np.sqrt(1 - ab) * eps, rtol=1e-6, atol=1e-6)
  out = process.target(x0, eps, levels)
  if prediction == "v":
    np.testing.assert_allclose(out, np.sqrt(ab) * eps - np.sqrt(1 - ab) * x0, atol=1e-6)
  x0_hat, eps_hat = process.to_x0_eps(x_t, levels, out)
  # eps from an x0 prediction divides by sqrt(1 - abar), tiny at low levels.
  tol = 2e-2 if prediction == "x0" else 2e-3
  np.testing.assert_allclose(x0_hat, x0, atol=tol)
  np.testing.assert_allclose(eps_hat, eps, atol=tol)


def test_flow_round_trip():
  process = FlowMatching()
  x0, eps, t = _random_case(flow=True)
  x_t = process.add_noise(x0, t, eps)
  tt = t[:, :, None, None, None]
  np.testing.assert_allclose(x_t, (1 - tt) * x0 + tt * eps, atol=1e-6)
  v = process.target(x0, eps, t)
  np.testing.assert_allclose(v, eps - x0, atol=1e-6)
  x0_hat, eps_hat = process.to_x0_eps(x_t, t, v)
  np.testing.assert_allclose(x0_hat, x0, atol=1e-5)
  np.testing.assert_allclose(eps_hat, eps, atol=1e-5)
  np.testing.assert_allclose(process.model_time(t), t * 1000, rtol=1e-6)


def test_clean_level_is_exact():
  process = GaussianDiffusion.create("linear")
  assert float(process.abar(jnp.asarray(-1))) == 1.0
  assert float(process.model_time(jnp.asarray(-1))) == 0.0
  np.testing.assert_array_equal(process.sampling_levels(10),
                                np.round(np.linspace(-1, 999, 11)).astype(int))


def test_scheduling_matrices():
  s, h = 4, 3
  full = scheduling_matrix("full_sequence", s, h)
  np.testing.assert_array_equal(full[:, 0], [4, 3, 2, 1, 0])
  assert (full == full[:, :1]).all()
  pyramid = scheduling_matrix("pyramid", s, h)
  assert pyramid.shape == (s + h, h)
  for i in range(s + h):
    for j in range(h):
      assert pyramid[i, j] == min(max(s + j - i, 0), s)
  auto = scheduling_matrix("autoregressive", s, h)
  assert auto.shape == (s * h + 1, h)
  for m in (full, pyramid, auto):
    assert (m[0] == s).all() and (m[-1] == 0).all()
    steps = m[:-1] - m[1:]
    assert ((steps >= 0) & (steps <= 1)).all() and (steps.sum(1) >= 1).all()
  # autoregressive: a frame starts denoising only once the previous one is clean
  for row in auto:
    for j in range(1, h):
      assert row[j] == s or row[j - 1] == 0
  with pytest.raises(ValueError, match="scheduling matrix must be one of"):
    scheduling_matrix("diagonal", s, h)


def _perfect_denoiser(process, x0_window):
  """A network that knows the clean window: returns the target implied by the true x0."""

  def denoise(x, levels):
    if isinstance(process, FlowMatching):
      t = levels[:, :, None, None, None]
      eps = (x - (1 - t) * x0_window) / jnp.maximum(t, 1e-6)
    else:
      ab = process.abar(levels)[:, :, None, None, None]
      eps = (x - jnp.sqrt(ab) * x0_window) / jnp.sqrt(jnp.maximum(1 - ab, 1e-12))
    return process.target(x0_window, eps, levels)

  return denoise


PROCESSES = {
    "ddim-eps": (GaussianDiffusion.create("linear", prediction="eps"), "ddim", 0.0),
    "ddim-v": (GaussianDiffusion.create("sigmoid", prediction="v"), "ddim", 0.0),
    "ddim-x0-eta": (GaussianDiffusion.create("cosine", prediction="x0"), "ddim", 0.5),
    "ddpm-v": (GaussianDiffusion.create("sigmoid", prediction="v"), "ddpm", 0.0),
    "euler-flow": (FlowMatching(), "euler", 0.0),
    "pndm-x0": (GaussianDiffusion.create("linear", prediction="x0"), "pndm", 0.0),
    "pndm_prk-eps": (GaussianDiffusion.create("linear", prediction="eps"), "pndm_prk", 0.0),
    "dpm_solver++-v": (GaussianDiffusion.create("sigmoid", prediction="v"), "dpm_solver++", 0.0),
}


@pytest.mark.parametrize("matrix", ["full_sequence", "pyramid", "autoregressive"])
@pytest.mark.parametrize("name", sorted(PROCESSES))
def test_sampler_with_perfect_denoiser_recovers_x0(name, matrix):
  process, sampler, eta = PROCESSES[name]
  context_level = 0.01 if sampler == "euler" else 15
  config = SamplerConfig(sampler=sampler, num_steps=10, eta=eta, matrix=matrix,
                         context_level=context_level)
  k1, k2, k3 = jax.random.split(jax.random.key(3), 3)
  c, h = 2, 3
  x0 = jax.random.normal(k1, (2, c + h, 4, 4, 3))
  context_in, context_levels = context_inputs(process, config, x0[:, :c])
  denoise = _perfect_denoiser(process, jnp.concatenate([context_in, x0[:, c:]], axis=1))
  noise = jax.random.normal(k2, (2, h, 4, 4, 3))
  out = sample_window(window_denoiser(denoise, context_in, context_levels), process, config,
                      noise, k3)
  np.testing.assert_allclose(out, x0[:, c:], atol=2e-4)


@pytest.mark.parametrize("name", sorted(PROCESSES))
def test_clip_denoised_bounds_the_samples(name):
  process, sampler, eta = PROCESSES[name]
  config = SamplerConfig(sampler=sampler, num_steps=5, eta=eta, clip_denoised=True,
                         context_level=0.01 if sampler == "euler" else 15)
  x0 = jnp.clip(jax.random.normal(jax.random.key(0), (2, 4, 4, 4, 3)), -1, 1)
  context = context_inputs(process, config, x0[:, :1])
  exact = sample_window(window_denoiser(_perfect_denoiser(process, x0), *context), process, config,
                        jnp.zeros((2, 3, 4, 4, 3)), jax.random.key(1))
  wild = sample_window(lambda x, levels: 50.0 * jnp.ones_like(x), process, config,
                       jax.random.normal(jax.random.key(2), (2, 3, 4, 4, 3)), jax.random.key(1))
  # PNDM's last step takes x0 back from a combination of noise estimates: float32 rounding
  assert float(jnp.abs(wild).max()) <= 1.0 + (1e-4 if sampler.startswith("pndm") else 1e-5)
  np.testing.assert_allclose(exact, x0[:, 1:], atol=2e-4)


def test_ddpm_step_is_the_posterior():
  """DDIM with eta=1 draws from q(x_s | x_t, x0) of DDPM, per frame."""
  process = GaussianDiffusion.create("linear", prediction="eps")
  x0, eps, _ = _random_case(1)
  level_from = jnp.array([[999, 500, 200, 40, 7]] * 2)
  level_to = jnp.array([[900, 300, 199, -1, 7]] * 2)
  x_t = process.add_noise(x0, level_from, eps)
  key = jax.random.key(5)
  got = ddim_step(process, x_t, level_from, level_to, process.target(x0, eps, level_from), key, 1.0)
  ab_t = process.abar(level_from)[:, :, None, None, None]
  ab_s = process.abar(level_to)[:, :, None, None, None]
  alpha = ab_t / ab_s
  mean = (jnp.sqrt(ab_s) * (1 - alpha) / (1 - ab_t) * x0
          + jnp.sqrt(alpha) * (1 - ab_s) / (1 - ab_t) * x_t)
  var = (1 - alpha) * (1 - ab_s) / (1 - ab_t)
  expected = mean + jnp.sqrt(var) * jax.random.normal(key, x_t.shape)
  expected = expected.at[:, 4].set(x_t[:, 4])  # level unchanged: frame kept
  np.testing.assert_allclose(got, expected, atol=1e-4)


def test_classifier_free_guidance():
  cond, null = jnp.array([2.0, 0.0]), jnp.array([1.0, 1.0])
  np.testing.assert_allclose(classifier_free_guidance(cond, null, 3.0), [4.0, -2.0])
  np.testing.assert_allclose(classifier_free_guidance(cond, null, 1.0), cond)


def test_training_regimes():
  rng = jax.random.key(0)
  gauss = GaussianDiffusion.create("linear")
  levels, mask = training_levels(gauss, rng, 64, 6, "irasim", num_context=2)
  assert (levels[:, :2] == -1).all()
  assert (levels[:, 2:] == levels[:, 2:3]).all()
  assert (levels[:, 2:] >= 0).all() and (levels < 1000).all()
  np.testing.assert_array_equal(mask[0], [0, 0, 1, 1, 1, 1])
  levels, mask = training_levels(gauss, rng, 64, 6, "per_frame")
  assert (mask == 1).all()
  assert (levels != levels[:, :1]).any(axis=1).mean() > 0.9  # independent per frame
  sorted_levels, mask = training_levels(gauss, rng, 64, 6, "monotone")
  assert (mask == 1).all()
  assert (jnp.diff(sorted_levels, axis=1) >= 0).all()  # never cleaner than an earlier frame
  np.testing.assert_array_equal(sorted_levels, jnp.sort(levels, axis=1))  # the same draws
  assert (levels != sorted_levels).any()
  levels, mask = training_levels(gauss, rng, 256, 6, "autoregressive", num_context=2)
  target = mask.argmax(axis=1)
  np.testing.assert_array_equal(mask.sum(axis=1), 1)  # one frame in the loss
  assert set(np.asarray(target).tolist()) == {2, 3, 4, 5}  # never a context frame
  before = jnp.arange(6)[None, :] < target[:, None]
  assert (jnp.where(before, levels, -1) == -1).all()  # a clean past
  assert (jnp.take_along_axis(levels, target[:, None], 1) >= 0).all()
  flow_levels, _ = training_levels(FlowMatching(), rng, 64, 6, "irasim", num_context=1)
  assert (flow_levels[:, 0] == 0.0).all() and ((flow_levels[:, 1:] > 0) & (flow_levels[:, 1:] < 1)).all()
  with pytest.raises(ValueError, match="noise regime"):
    training_levels(gauss, rng, 2, 6, "shared")
  with pytest.raises(ValueError, match="num_context"):
    training_levels(gauss, rng, 2, 6, "irasim", num_context=6)


def test_level_sampling_shifts_training_towards_noise():
  rng = jax.random.key(0)
  gauss = GaussianDiffusion.create("sigmoid")
  default = gauss.sample_levels(rng, (4096,))
  np.testing.assert_array_equal(default, jax.random.randint(rng, (4096,), 0, 1000))  # unchanged
  np.testing.assert_array_equal(gauss.sample_levels(rng, (4096,), LevelSampling("uniform")),
                                default)
  shifted = gauss.sample_levels(rng, (4096,), LevelSampling("logit_normal", loc=1.0))
  assert shifted.dtype == jnp.int32 and (shifted >= 0).all() and (shifted <= 999).all()
  assert 0.8 < float((shifted >= 500).mean()) < 0.88  # P(N(1, 1) > 0) = 0.84
  assert abs(float(jnp.median(default)) - 500) < 30
  centred = gauss.sample_levels(rng, (4096,), LevelSampling("logit_normal", loc=0.0, scale=0.5))
  assert abs(float((centred >= 500).mean()) - 0.5) < 0.03
  assert float(jnp.std(centred)) < float(jnp.std(default))
  flow = FlowMatching()
  np.testing.assert_allclose(flow.sample_levels(rng, (64,)),
                             flow.sample_levels(rng, (64,), LevelSampling("logit_normal")))
  assert float(jnp.mean(flow.sample_levels(rng, (4096,), LevelSampling("uniform")))) == \
      pytest.approx(0.5, abs=0.02)
  levels, mask = training_levels(gauss, rng, 512, 2, "irasim", 1,
                                 LevelSampling("logit_normal", loc=2.0))
  assert (levels[:, 0] == -1).all() and float(jnp.mean(levels[:, 1])) > 750
  with pytest.raises(ValueError, match="level distribution must be one of"):
    LevelSampling("lognormal")
  with pytest.raises(ValueError, match="scale must be > 0"):
    LevelSampling("logit_normal", scale=0.0)


@pytest.mark.parametrize("regime,expect_zero", [("irasim", True), ("per_frame", False)])
def test_loss_only_on_predicted_frames_in_irasim_regime(regime, expect_zero):
  """A denoiser exact on frames 1.. and wrong on frame 0 has zero loss only when frame 0 is context."""
  process = GaussianDiffusion.create("linear", prediction="v")
  x0 = jax.random.normal(jax.random.key(0), SHAPE)

  def denoise(x_t, levels):
    ab = process.abar(levels)[:, :, None, None, None]
    eps = (x_t - jnp.sqrt(ab) * x0) / jnp.sqrt(jnp.maximum(1 - ab, 1e-12))
    return process.target(x0, eps, levels).at[:, 0].add(1.0)

  loss, aux = diffusion_loss(denoise, process, x0, jax.random.key(1), regime, num_context=1)
  assert aux["per_frame_loss"].shape == SHAPE[:2]
  if expect_zero:
    assert float(loss) < 1e-6
  else:
    assert float(loss) > 0.1


def test_object_weights_come_from_the_previous_frame():
  """A 1-pixel object on a flat background: the values within ``dilation`` of where the previous
  frame shows it weigh 1 + w, whatever the predicted frame shows; an error there costs 1 + w
  times an error elsewhere."""
  x0 = -np.ones((1, 3, 6, 6, 3), np.float32)
  x0[0, 0, 1, 1] = x0[0, 1, 4, 4] = 1.0  # frame 2 is empty: its weights come from frame 1
  weights = np.asarray(object_weights(jnp.asarray(x0), 9.0, 1))[..., 0]
  assert weights.shape == (1, 3, 6, 6) and (weights[0, 0] == 1).all()
  assert (weights[0, 1, 0:3, 0:3] == 10).all() and (weights[0, 1] == 10).sum() == 9
  assert (weights[0, 2, 3:6, 3:6] == 10).all() and (weights[0, 2] == 10).sum() == 9
  assert (np.asarray(object_weights(jnp.asarray(x0), 9.0, 0))[0, 2, ..., 0] == 10).sum() == 1
  process = GaussianDiffusion.create("linear", prediction="x0")
  levels, mask = jnp.zeros((1, 3), jnp.int32), jnp.asarray([[0.0, 0.0, 1.0]])
  noise = jnp.zeros(x0.shape)

  def loss(where, weight):  # x0 prediction, wrong by 1 at one pixel of frame 2
    return float(masked_loss_sum(lambda x, lv: jnp.asarray(x0).at[0, 2, where[0], where[1]].add(
        1.0), process, jnp.asarray(x0), levels, noise, mask, weight, 1)[0])

  assert loss((5, 5), 9.0) == pytest.approx(10 * loss((0, 5), 9.0))
  assert loss((5, 5), 0.0) == pytest.approx(loss((0, 5), 0.0))


def test_regression_process_is_one_deterministic_step():
  from wmjax.diffusion import Regression, make_process
  process = make_process("regression")
  assert isinstance(process, Regression)
  x0 = jnp.linspace(-1, 1, 2 * 3 * 4).reshape(2, 3, 4)
  levels, mask = training_levels(process, jax.random.key(0), 2, 3, "irasim", 1)
  np.testing.assert_array_equal(levels, [[0, 1, 1]] * 2)  # clean context, pure-noise targets
  np.testing.assert_array_equal(mask, [[0, 1, 1]] * 2)
  noise = jax.random.normal(jax.random.key(1), x0.shape)
  shown = process.add_noise(x0, levels, noise)
  np.testing.assert_array_equal(shown[:, 0], x0[:, 0])
  np.testing.assert_array_equal(shown[:, 1:], noise[:, 1:])
  np.testing.assert_array_equal(process.target(x0, None, levels), x0)
  # the sampler's one step returns the network output as the frames
  config = SamplerConfig(sampler="euler", num_steps=1, context_level=0.0)
  out = sample_window(lambda x, lv: x + 0.5, process, config, jnp.zeros((2, 2, 4)),
                      jax.random.key(2))
  np.testing.assert_allclose(out, 0.5)
  with pytest.raises(ValueError, match="num_steps must be 1"):
    process.sampling_levels(10)
