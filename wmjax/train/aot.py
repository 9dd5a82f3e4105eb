"""``wmjax compile``: a config's train step or rollout block compiled ahead of time for a device
target it need not run on (:func:`wmjax.train.fit.parse_target`), with XLA's memory report.

The train step is the one a run trains with: :func:`wmjax.train.context.build_context` builds its
mesh, model and trainer on the target's devices, and :func:`wmjax.train.context.compile_step`
compiles it.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import ml_collections

from wmjax.model import WorldModel
from wmjax.nn import attention
from wmjax.rollout import block_flops, rollout
from wmjax.train.context import build_context, compile_step, fit_context
from wmjax.train.fit import Target, cost_report, memory_report


def compile_train(config: ml_collections.ConfigDict, target: Target, batch: int | None = None,
                  budget_bytes: int | None = None) -> dict:
  """The report of :func:`wmjax.train.context.compile_step` for the train step of ``config`` on
  ``target`` at global ``batch`` (default ``config.batch_size``)."""
  return compile_step(build_context(config, target), batch, budget_bytes)[1]


def compile_rollout(config: ml_collections.ConfigDict, target: Target, batch: int | None = None,
                    budget_bytes: int | None = None) -> dict:
  """One rollout block (``rollout.context`` frames in, ``rollout.horizon`` out, with the config's
  sampler) jitted and compiled for the first device of ``target`` at ``batch`` rollouts (default
  8; a ``model.fp8_matmuls`` network with calibrated float8 scales) -> its report, as
  :func:`compile_train`'s (memory, fits, FLOPs, predicted time, compile time)."""
  world_model = WorldModel.from_config(config)
  net = world_model.network
  batch = batch or 8
  c, h = config.rollout.context, config.rollout.horizon
  shape = tuple(config.frame_shape)
  device = jax.sharding.SingleDeviceSharding(target.devices[0])
  start = time.perf_counter()
  with attention.platform_override(target.platform):
    params = jax.eval_shape(lambda: world_model.init(jax.random.key(0), shape, frames=c + h))
    if net.fp8_matmuls:  # as a calibrated model runs: with static float8 scales
      params = jax.eval_shape(lambda p: world_model.calibrate_float8(
          p, jnp.zeros((1, c + h) + shape), jnp.zeros((1, c + h - 1, net.action_dim)),
          jax.random.key(0), context=c), params)
    params = jax.tree.map(lambda p: jax.ShapeDtypeStruct(p.shape, p.dtype, sharding=device),
                          params)
    run = jax.jit(lambda p, context, actions, key: rollout(
        world_model, p, context, actions, jax.random.wrap_key_data(key), horizon=h))
    compiled = run.lower(
        params, jax.ShapeDtypeStruct((batch, c) + shape, jnp.float32, sharding=device),
        jax.ShapeDtypeStruct((batch, h, net.action_dim), jnp.float32, sharding=device),
        jax.ShapeDtypeStruct((2,), jnp.uint32, sharding=device)).compile()
  calls = world_model.sampler.model_calls(h) * (2 if world_model.guided else 1)
  return {
      "what": "rollout", "target": target.spec, "platform": target.platform, "devices": 1,
      "batch": batch, "context": c, "horizon": h, "sampler": config.sampling.sampler,
      "model_calls": calls, "dtype": str(net.dtype),
      "attention": attention.resolve_backend(net.attention_impl, net.dtype, target.platform),
      **memory_report(compiled, target, budget_bytes), **cost_report(compiled, target),
      "analytic_flops": block_flops(world_model, batch, c, h, shape[0], shape[1]),
      "compile_s": time.perf_counter() - start,
  }


def compile_report(config: ml_collections.ConfigDict, target: Target, what: str = "train",
                   batch: int | None = None, budget_bytes: int | None = None, log=print) -> dict:
  """The report of :func:`compile_train` (``what='train'``) or :func:`compile_rollout`
  (``'rollout'``) for ``target``. A train step that does not fit also gets ``auto_fit``: the
  setting :func:`wmjax.train.context.fit_context` would choose (remat, grad_accum, its size, its
  predicted step time and what was tried)."""
  if what == "rollout":
    return compile_rollout(config, target, batch, budget_bytes)
  context = build_context(config, target)
  report = compile_step(context, batch, budget_bytes)[1]
  if report["fits"] is False:
    _, chosen = fit_context(context, budget_bytes, batch, first=(context, report), log=log)
    report["auto_fit"] = {"remat": chosen["remat"], "grad_accum": chosen["grad_accum"],
                          "total_gib": chosen["total_gib"],
                          "predicted_ms": chosen.get("predicted_ms"), "tried": chosen["tried"]}
  return report
