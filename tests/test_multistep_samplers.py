"""PNDM (PLMS, with and without its Runge-Kutta warm-up) and DPM-Solver++ 2M against diffusers'
schedulers, step by step, and inside :func:`sample_window` with per-frame chains."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wmjax.diffusion import FlowMatching, GaussianDiffusion, SamplerConfig, sample_window
from wmjax.diffusion.sampling import (frame_steps, init_memory, sampler_step, sampler_update,
                                      scheduling_matrix)

pytestmark = pytest.mark.unit

DIFFUSERS_PREDICTION = {"eps": "epsilon", "v": "v_prediction", "x0": "sample"}


def _network(lib, x, t):
  """A made-up network output, nonlinear in the sample and the level; ``lib`` is jnp or torch."""
  return lib.tanh(1.5 * x) * (0.5 + t / 2000.0) + 0.05 * lib.cos(t / 50.0)


def _diffusers_scheduler(sampler, process, num_steps):
  """diffusers' scheduler for ``sampler`` on the process's own float32 signal table, with the
  project's level spacing (``trailing``) and its clean end point. PNDM is given noise estimates
  (:func:`_diffusers_chain`)."""
  torch = pytest.importorskip("torch")
  schedulers = pytest.importorskip("diffusers.schedulers")
  common = dict(num_train_timesteps=process.num_timesteps, timestep_spacing="trailing")
  if sampler in ("pndm", "pndm_prk"):
    scheduler = schedulers.PNDMScheduler(skip_prk_steps=sampler == "pndm", set_alpha_to_one=True,
                                         prediction_type="epsilon", **common)
  else:
    scheduler = schedulers.DPMSolverMultistepScheduler(
        algorithm_type="dpmsolver++", solver_order=2, solver_type="midpoint",
        lower_order_final=True, final_sigmas_type="zero",
        prediction_type=DIFFUSERS_PREDICTION[process.prediction], **common)
  table = np.array(process.abar(jnp.arange(process.num_timesteps)))
  scheduler.alphas_cumprod = torch.from_numpy(table)
  scheduler.set_timesteps(num_steps)
  return scheduler


def _noise_estimate(process, scheduler, sample, t, out):
  """The network output ``out`` as a noise estimate, in torch.

  diffusers' PNDM combines raw v outputs and converts the combination with the current sample;
  the project's converts every output at its own sample and level (the estimates PLMS is about),
  so diffusers is given those noise estimates."""
  ab = scheduler.alphas_cumprod[t]
  if process.prediction == "v":
    return ab.sqrt() * out + (1 - ab).sqrt() * sample
  if process.prediction == "x0":
    return (sample - ab.sqrt() * out) / (1 - ab).sqrt()
  return out


def _diffusers_chain(process, scheduler, x):
  """(timesteps, latents after every step) of diffusers' loop from ``x``: the timestep of every
  network call and the latent it sees next."""
  torch = pytest.importorskip("torch")
  is_pndm = type(scheduler).__name__ == "PNDMScheduler"
  sample, latents = torch.from_numpy(np.array(x)), []
  for t in scheduler.timesteps:
    out = _network(torch, sample, torch.tensor(float(t)))
    if is_pndm:
      out = _noise_estimate(process, scheduler, sample, t, out)
    sample = scheduler.step(out, t, sample, return_dict=False)[0]
    latents.append(sample.numpy())
  return scheduler.timesteps.numpy(), latents


def _our_chain(process, config, x):
  """(levels the network sees, latents after every step) of the sampler's own loop from ``x``."""
  steps = frame_steps(process, config, x.shape[1])
  memory, levels, latents = init_memory(config, x), [], []
  for row in zip(*steps):
    step = type(steps)(*(jnp.broadcast_to(a, x.shape[:2]) for a in row))
    out = _network(jnp, x, jnp.asarray(step.level_from, jnp.float32)[..., None])
    x, memory = sampler_update(process, config, x, memory, step, out, jax.random.key(0))
    levels.append(int(row[0][0]))
    latents.append(np.asarray(x))
  return np.array(levels), latents


# PNDM works on noise estimates: from a v or x0 network at a level whose signal is tiny (cosine
# and sigmoid schedules end near abar = 1e-9 and 3e-7) they carry float32 rounding that its
# step multiplies by sqrt(abar' / abar), in diffusers and here alike; those are checked on the
# linear schedule.
CASES = {"pndm": [("linear", "eps", 10), ("linear", "eps", 20), ("linear", "eps", 50),
                  ("linear", "v", 20), ("linear", "x0", 20), ("sigmoid", "eps", 20),
                  ("cosine", "eps", 10)],
         "pndm_prk": [("linear", "eps", 10), ("linear", "eps", 50), ("linear", "v", 20)],
         "dpm_solver++": [("linear", "eps", 10), ("linear", "eps", 20), ("linear", "eps", 50),
                          ("linear", "v", 20), ("sigmoid", "eps", 20), ("cosine", "v", 10),
                          ("sigmoid", "x0", 20)]}


@pytest.mark.parametrize("sampler,schedule,prediction,num_steps",
                         [(sampler, *case) for sampler, cases in CASES.items() for case in cases])
def test_multistep_sampler_equals_diffusers_step_by_step(sampler, schedule, prediction, num_steps):
  process = GaussianDiffusion.create(schedule, 1000, prediction)
  x = jax.random.normal(jax.random.key(1), (2, 1, 6), jnp.float32)
  config = SamplerConfig(sampler=sampler, num_steps=num_steps)
  timesteps, expected = _diffusers_chain(process, _diffusers_scheduler(sampler, process, num_steps), x)
  levels, latents = _our_chain(process, config, x)
  np.testing.assert_array_equal(levels, timesteps)
  extra_calls = {"pndm": 1, "pndm_prk": 9}.get(sampler, 0)
  assert len(latents) == config.model_calls(1) == num_steps + extra_calls
  for i, (ours, theirs) in enumerate(zip(latents, expected)):
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5, err_msg=f"step {i}")


def test_pndm_one_step_is_one_call_and_ddim():
  process = GaussianDiffusion.create("linear", 1000, "eps")
  x = jax.random.normal(jax.random.key(3), (1, 1, 5), jnp.float32)
  config = SamplerConfig(sampler="pndm", num_steps=1)
  assert config.model_calls(1) == 1
  _, (latent,) = _our_chain(process, config, x)
  ddim = sampler_step(process, SamplerConfig(num_steps=1), x, jnp.full((1, 1), 999),
                      jnp.full((1, 1), -1), _network(jnp, x, 999.0), jax.random.key(0))
  np.testing.assert_allclose(latent, ddim, rtol=1e-6)


@pytest.mark.parametrize("num_steps", [1, 3])
def test_pndm_prk_below_four_steps_is_all_runge_kutta_to_clean(num_steps):
  """diffusers' warm-up would stop short of clean below four steps; here every step is one."""
  process = GaussianDiffusion.create("linear", 1000, "eps")
  config = SamplerConfig(sampler="pndm_prk", num_steps=num_steps)
  steps = frame_steps(process, config, 1)
  assert config.model_calls(1) == 4 * num_steps
  assert steps.level_to[-1, 0] == process.clean_level
  np.testing.assert_array_equal(steps.level_from[::4, 0], process.sampling_levels(num_steps)[:0:-1])


def test_dpm_solver_with_two_steps_is_ddim():
  """Its first step has no previous estimate and its last goes to clean: both first order."""
  process = GaussianDiffusion.create("sigmoid", 1000, "x0")
  noise = jax.random.normal(jax.random.key(7), (2, 1, 5))
  denoise = lambda x, levels: _network(jnp, x, levels[..., None].astype(jnp.float32))
  dpm = sample_window(denoise, process, SamplerConfig("dpm_solver++", 2), noise, jax.random.key(0))
  ddim = sample_window(denoise, process, SamplerConfig("ddim", 2), noise, jax.random.key(0))
  three = sample_window(denoise, process, SamplerConfig("dpm_solver++", 3), noise, jax.random.key(0))
  np.testing.assert_allclose(dpm, ddim, rtol=1e-5, atol=1e-6)
  assert not np.allclose(three, sample_window(denoise, process, SamplerConfig("ddim", 3), noise,
                                              jax.random.key(0)), atol=1e-4)


@pytest.mark.parametrize("sampler", ["pndm", "pndm_prk", "dpm_solver++"])
def test_autoregressive_matrix_gives_every_frame_its_own_chain(sampler):
  """With the autoregressive matrix each frame runs the same chain as a lone frame would, given
  a network that treats frames independently; the result is finite and deterministic."""
  process = GaussianDiffusion.create("linear", 1000, "eps")
  config = SamplerConfig(sampler=sampler, num_steps=6, matrix="autoregressive")
  noise = jax.random.normal(jax.random.key(4), (2, 3, 4, 4, 3))
  denoise = lambda x, levels: _network(jnp, x, levels[..., None, None, None].astype(jnp.float32))
  run = jax.jit(lambda n, k: sample_window(denoise, process, config, n, k))
  out = run(noise, jax.random.key(5))
  assert out.shape == noise.shape and bool(jnp.all(jnp.isfinite(out)))
  np.testing.assert_array_equal(out, run(noise, jax.random.key(6)))
  alone = SamplerConfig(sampler=sampler, num_steps=6)
  for j in range(3):
    single = sample_window(denoise, process, alone, noise[:, j:j + 1], jax.random.key(0))
    np.testing.assert_allclose(out[:, j:j + 1], single, rtol=1e-5, atol=1e-5)
  assert config.model_calls(3) == 3 * alone.model_calls(1)
  assert len(scheduling_matrix("autoregressive", config.num_stages, 3)) - 1 == config.model_calls(3)


@pytest.mark.parametrize("sampler", ["pndm", "pndm_prk", "dpm_solver++"])
def test_multistep_samplers_refuse_flow_matching_and_eta(sampler):
  config = SamplerConfig(sampler=sampler, num_steps=4)
  with pytest.raises(ValueError, match="does not fit FlowMatching"):
    sample_window(lambda x, levels: x, FlowMatching(), config, jnp.zeros((1, 2, 3)),
                  jax.random.key(0))
  with pytest.raises(ValueError, match="deterministic"):
    SamplerConfig(sampler=sampler, eta=0.5)
  with pytest.raises(ValueError, match="multistep"):
    sampler_step(GaussianDiffusion.create(), config, jnp.zeros((1, 1, 3)), jnp.zeros((1, 1)),
                 jnp.zeros((1, 1)), jnp.zeros((1, 1, 3)), jax.random.key(0))
