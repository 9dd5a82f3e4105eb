"""Compile the train step for a device target, with or without its hardware, and fit a config.

``compile_train(config, target, batch)`` builds the exact sharded train step of
:class:`wmjax.train.step.ShardedTrainer` on the target's devices and compiles it; XLA's memory
analysis then says what one device needs (arguments, outputs, temporaries). Targets:

``cpu:N``          N host devices (simulated: ``jax_num_cpu_devices``)
``h100[:N]``       N H100 80GB; ``h200[:N]`` (141 GB), ``a100[:N]`` (A100 80GB) — compiled on any
                   machine where JAX's CUDA plugin is installed (no GPU needed)
``v5p:2x2x1`` ...  a Cloud TPU topology (``v4``, ``v5e``, ``v5p``, ``v6e``); needs libtpu
``local``          the devices this process sees (what the trainer uses)

``fit_train(config, target, batch)`` climbs the ladder remat none -> dots -> full, then
gradient-accumulation micro-batches 2, 4, 8, ... (with full remat) from the config's own setting
until the compiled step fits the device's memory, and says what it chose and what it tried.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import re
import time

import jax
import jax.numpy as jnp
import ml_collections

from wmjax import parallel
from wmjax.nn import attention, forward_flops
from wmjax.model import WorldModel
from wmjax.rollout import block_flops, rollout
from wmjax.errors import RunError
from wmjax.train.step import ShardedTrainer

GIB = 1024 ** 3
REMAT_LADDER = ("none", "dots", "full")


def _gpu_target(description: str, cores: int, fpus: int, capability: tuple[int, int],
                shared_per_core: int, shared_optin: int, l2: int, clock_ghz: float,
                bandwidth: float, memory: int) -> str:
  """An XLA ``GpuTargetConfig`` in text form: what XLA's GPU compiler needs of a card."""
  return (
      f"gpu_device_info {{ threads_per_block_limit: 1024 threads_per_warp: 32 "
      f"shared_memory_per_block: 49152 shared_memory_per_core: {shared_per_core} "
      f"threads_per_core_limit: 2048 core_count: {cores} fpus_per_core: {fpus} "
      f"block_dim_limit_x: 2147483647 block_dim_limit_y: 65535 block_dim_limit_z: 65535 "
      f"memory_bandwidth: {int(bandwidth)} l2_cache_size: {l2} clock_rate_ghz: {clock_ghz} "
      f"device_memory_size: {memory} shared_memory_per_block_optin: {shared_optin} "
      f"cuda_compute_capability {{ major: {capability[0]} minor: {capability[1]} }} "
      f"registers_per_core_limit: 65536 registers_per_block_limit: 65536 }} "
      f'platform_name: "CUDA" dnn_version_info {{ major: 9 minor: 8 }} '
      f'runtime_version {{ major: 12 minor: 8 }} device_description_str: "{description}"')


# name: (GpuTargetConfig text, device memory in bytes)
GPU_TARGETS = {
    "h100": _gpu_target("NVIDIA H100 80GB HBM3", 132, 128, (9, 0), 233472, 232448, 52428800,
                        1.98, 3.35232e12, 84929347584),
    "h200": _gpu_target("NVIDIA H200", 132, 128, (9, 0), 233472, 232448, 62914560, 1.98,
                        4.8e12, 150754820096),
    "a100": _gpu_target("NVIDIA A100-SXM4-80GB", 108, 64, (8, 0), 167936, 166912, 41943040,
                        1.41, 2.039e12, 85899345920),
}
# TPU generation: HBM per chip in bytes (the topology itself comes from libtpu).
TPU_MEMORY = {"v4": 32 * GIB, "v5e": 16 * GIB, "v5litepod": 16 * GIB, "v5p": 95 * GIB,
              "v6e": 32 * GIB}


@dataclasses.dataclass(frozen=True)
class Target:
  """Devices to compile for: ``platform`` ('cpu' / 'gpu' / 'tpu'), the devices (real or from a
  topology description) and the memory one device has (None: unknown, e.g. the host CPU)."""

  spec: str
  platform: str
  devices: tuple
  memory_bytes: int | None


def parse_target(spec: str) -> Target:
  """A :class:`Target` from ``cpu:N``, ``h100[:N]``, ``h200[:N]``, ``a100[:N]``, a TPU topology
  such as ``v5p:2x2x1`` or ``local``; ValueError naming the accepted forms otherwise."""
  name, _, count = spec.partition(":")
  forms = ("cpu:N, h100[:N], h200[:N], a100[:N], a TPU topology such as v5p:2x2x1 / v5e:4x4 / "
           "v6e:2x2, or local")
  if name == "local":
    devices = jax.devices()
    # memory_stats answers only for this process's devices (several processes: jax.distributed)
    stats = jax.local_devices()[0].memory_stats() or {}
    return Target(spec, devices[0].platform, tuple(devices), stats.get("bytes_limit"))
  if name == "cpu" or name in GPU_TARGETS:
    if count and not count.isdigit() or count == "0":
      raise ValueError(f"target {spec!r}: the device count after ':' must be a positive integer")
    n = int(count or 1)
  if name == "cpu":
    devices = jax.devices("cpu")
    if n > len(devices):
      raise ValueError(f"target {spec!r} needs {n} CPU devices but this process has "
                       f"{len(devices)}; set jax.config.update('jax_num_cpu_devices', {n}) before "
                       f"JAX starts (wmjax compile does)")
    return Target(spec, "cpu", tuple(devices[:n]), None)
  from jax.experimental import topologies
  if name in GPU_TARGETS:
    os.environ.setdefault("JAX_SKIP_CUDA_CONSTRAINTS_CHECK", "1")
    try:
      topology = topologies.get_topology_desc(platform="cuda", target_config=GPU_TARGETS[name],
                                              topology=f"1x1x{n}")
    except Exception as e:  # the plugin is missing or cannot describe the card
      raise ValueError(f"target {spec!r} needs JAX's CUDA plugin (pip install "
                       f"'jax[cuda12]=={jax.__version__}'; no GPU needed): {e}") from e
    return Target(spec, "gpu", tuple(topology.devices), _gpu_memory(name))
  generation = name.lower()
  if generation in TPU_MEMORY and count:
    # Only a description of the topology is made: other processes may hold libtpu's lock file,
    # and no TPU metadata server is asked.
    os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
    os.environ.setdefault("TPU_SKIP_MDS_QUERY", "1")
    try:
      topology = topologies.get_topology_desc(topology_name=spec, platform="tpu")
    except Exception as e:
      raise ValueError(f"target {spec!r} needs libtpu (pip install 'jax[tpu]=={jax.__version__}'"
                       f"; no TPU needed) and a valid topology: {e}") from e
    return Target(spec, "tpu", tuple(topology.devices), TPU_MEMORY[generation])
  raise ValueError(f"unknown compile target {spec!r}; expected {forms}")


def _gpu_memory(name: str) -> int:
  text = GPU_TARGETS[name]
  return int(text.split("device_memory_size: ")[1].split()[0])


def usable_memory(target: Target) -> int | None:
  """Bytes JAX's allocator may take on one device of ``target``: the card's memory times
  ``XLA_PYTHON_CLIENT_MEM_FRACTION`` (default 0.75) on GPU, the whole HBM on TPU, the live
  allocator's limit for ``local``."""
  if target.memory_bytes is None or target.spec == "local" or target.platform != "gpu":
    return target.memory_bytes
  return int(target.memory_bytes * float(os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION", 0.75)))


def memory_report(compiled: jax.stages.Compiled, target: Target,
                  budget_bytes: int | None = None) -> dict:
  """Per-device GiB of a compiled program (arguments, outputs, temporaries, total: arguments and
  outputs counted once where they alias), the device's memory and whether the total fits
  ``budget_bytes`` (default: :func:`usable_memory`; None when neither is known)."""
  analysis = compiled.memory_analysis()
  args, out = analysis.argument_size_in_bytes, analysis.output_size_in_bytes
  temp, alias = analysis.temp_size_in_bytes, analysis.alias_size_in_bytes
  total = args + out - alias + temp
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) and cost else cost
  xla_flops = float(cost.get("flops", 0.0)) if isinstance(cost, dict) else 0.0
  return {
      "arguments_gib": args / GIB, "outputs_gib": out / GIB, "temp_gib": temp / GIB,
      "total_gib": total / GIB, **_device_memory(target, budget_bytes, total),
      "xla_flops_per_device": xla_flops or None,
  }


def _device_memory(target: Target, budget_bytes: int | None, total: int | None) -> dict:
  """The device's memory, the limit (``budget_bytes``, default :func:`usable_memory`) in GiB and
  whether ``total`` bytes fit it (None when no limit is known; False when ``total`` is None: the
  compiler refused the program)."""
  limit = budget_bytes if budget_bytes is not None else usable_memory(target)
  return {
      "device_memory_gib": None if target.memory_bytes is None else target.memory_bytes / GIB,
      "limit_gib": None if limit is None else limit / GIB,
      "fits": False if total is None else None if limit is None else total <= limit,
  }


_REFUSED_TEMP = re.compile(r"temporaries \(([\d.]+)([KMGT])i?B?\)")


def refused_report(error: Exception, target: Target, budget_bytes: int | None = None
                   ) -> dict | None:
  """The report of a program the compiler refused for want of device memory (a TPU compiler
  raises ``RESOURCE_EXHAUSTED`` rather than emit a program larger than the HBM): ``fits`` False,
  ``temp_gib`` the temporaries the message names (None when it names none), the other sizes None
  and ``refused`` the message's first line. None for any other error."""
  message = str(error)
  if not message.startswith("RESOURCE_EXHAUSTED"):
    return None
  found = _REFUSED_TEMP.search(message)
  temp = (float(found.group(1)) * 1024 ** ("KMGT".index(found.group(2)) - 2)) if found else None
  return {
      "arguments_gib": None, "outputs_gib": None, "temp_gib": temp, "total_gib": temp,
      **_device_memory(target, budget_bytes, None),
      "xla_flops_per_device": None, "refused": message.splitlines()[0],
  }


def compile_step(config: ml_collections.ConfigDict, target: Target, batch: int | None = None,
                 budget_bytes: int | None = None
                 ) -> tuple[ShardedTrainer, jax.stages.Compiled, dict]:
  """The sharded train step of ``config`` compiled for ``target`` at global ``batch`` (default
  ``config.batch_size``) -> (trainer, compiled step, report): per-device memory (GiB) and whether
  it fits (:func:`memory_report`), the mesh, the attention path, XLA's and the analytic FLOPs and
  the compile time. The trainer's :meth:`~ShardedTrainer.step` reuses the compiled step. A step
  the compiler refuses for want of memory comes back as None with :func:`refused_report`."""
  world_model = WorldModel.from_config(config)
  net = world_model.network
  batch = batch or config.batch_size
  frames = config.data.frames if "data" in config else net.num_frames
  shape = tuple(config.frame_shape)
  mesh = parallel.make_mesh(tuple(config.mesh), list(target.devices))
  parallel.check_batch_divisible(batch, mesh, what="global batch_size")
  start = time.perf_counter()
  with attention.platform_override(target.platform):
    trainer = ShardedTrainer(world_model, config, mesh, shape, frames)
    frames_struct = jax.ShapeDtypeStruct((batch, frames) + shape, jnp.float32,
                                         sharding=trainer.batch_sharding)
    actions_struct = jax.ShapeDtypeStruct((batch, frames - 1, net.action_dim), jnp.float32,
                                          sharding=trainer.batch_sharding)
    try:
      compiled = trainer.compile(trainer.abstract_state, frames_struct, actions_struct)
      memory = memory_report(compiled, target, budget_bytes)
    except jax.errors.JaxRuntimeError as e:
      compiled, memory = None, refused_report(e, target, budget_bytes)
      if memory is None:
        raise
  report = {
      "what": "train", "target": target.spec, "platform": target.platform,
      "devices": len(target.devices), "mesh": dict(mesh.shape), "batch": batch, "frames": frames,
      "remat": net.remat, "grad_accum": trainer.micro_batches, "dtype": str(net.dtype),
      "attention": attention.resolve_backend(net.attention_impl, net.dtype, target.platform),
      **memory,
      "analytic_flops": 3 * forward_flops(net, batch, frames, shape[0], shape[1]),
      "compile_s": time.perf_counter() - start,
  }
  return trainer, compiled, report


def compile_train(config: ml_collections.ConfigDict, target: Target, batch: int | None = None,
                  budget_bytes: int | None = None) -> dict:
  """The report of :func:`compile_step`."""
  return compile_step(config, target, batch, budget_bytes)[2]


def compile_rollout(config: ml_collections.ConfigDict, target: Target, batch: int | None = None,
                    budget_bytes: int | None = None) -> dict:
  """One rollout block (``rollout.context`` frames in, ``rollout.horizon`` out, with the config's
  sampler) jitted and compiled for the first device of ``target`` at ``batch`` rollouts (default
  8) -> the report of :func:`compile_step` for it."""
  world_model = WorldModel.from_config(config)
  net = world_model.network
  batch = batch or 8
  c, h = config.rollout.context, config.rollout.horizon
  shape = tuple(config.frame_shape)
  device = jax.sharding.SingleDeviceSharding(target.devices[0])
  start = time.perf_counter()
  with attention.platform_override(target.platform):
    params = jax.eval_shape(lambda: world_model.init(jax.random.key(0), shape, frames=c + h))
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
      **memory_report(compiled, target, budget_bytes),
      "analytic_flops": block_flops(world_model, batch, c, h, shape[0], shape[1]),
      "compile_s": time.perf_counter() - start,
  }


def fit_ladder(config: ml_collections.ConfigDict, batch: int, data_parallel: int
               ) -> list[tuple[str, int]]:
  """(remat, grad_accum) settings from the config's own upward: more remat first, then more
  micro-batches with full remat (as long as each device keeps at least one sample)."""
  remat = config.model.remat
  accum = config.optim.grad_accum
  start = REMAT_LADDER.index(remat) if remat in REMAT_LADDER else 0
  ladder = [(r, accum) for r in REMAT_LADDER[start:]]
  k = accum * 2
  while batch % (data_parallel * k) == 0:
    ladder.append(("full", k))
    k *= 2
  return ladder


def with_setting(config: ml_collections.ConfigDict, remat: str, grad_accum: int
                 ) -> ml_collections.ConfigDict:
  """A copy of ``config`` with ``model.remat`` and ``optim.grad_accum`` set."""
  updated = copy.deepcopy(config)
  with updated.unlocked():
    updated.model.remat = remat
    updated.optim.grad_accum = grad_accum
  return updated


class DoesNotFitError(RunError):
  """No setting of the fit ladder compiles to a step that fits the device's memory."""


def _limit(target: Target, budget_bytes: int | None) -> int:
  limit = budget_bytes if budget_bytes is not None else usable_memory(target)
  if limit is None:
    raise ValueError(f"target {target.spec!r} reports no memory size: give a budget "
                     f"(train.memory_budget_gib / --budget_gib)")
  return limit


def describe(report: dict) -> str:
  """One line: the setting, its compiled GiB per device against the limit, fits or not."""
  setting = (f"remat={report['remat']} grad_accum={report['grad_accum']}"
             if report["what"] == "train" else f"{report['model_calls']} model calls")
  verdict = ("" if report["fits"] is None else
             f" of {report['limit_gib']:.3g} -> {'fits' if report['fits'] else 'does not fit'}")
  head = f"{report['what']} on {report['target']} (batch {report['batch']}, {setting}): "
  if report.get("refused"):
    return (f"{head}more than {_gib(report['temp_gib'])} GiB per device, refused by the "
            f"compiler{verdict} ({report['refused']})")
  return (f"{head}{report['total_gib']:.3g} GiB per device (arguments "
          f"{report['arguments_gib']:.3g} + temp {report['temp_gib']:.3g}){verdict}")


def _gib(value: float | None) -> str:
  return "an unknown number of" if value is None else f"{value:.3g}"


def fit_step(config: ml_collections.ConfigDict, target: Target, budget_bytes: int | None = None,
             batch: int | None = None, first: tuple | None = None, log=print
             ) -> tuple[ml_collections.ConfigDict, ShardedTrainer, dict]:
  """The first setting of :func:`fit_ladder` whose compiled step fits ``budget_bytes`` (default:
  what the target's allocator may take) -> (config with that setting, its trainer with the step
  compiled, its report with ``tried``). ``first``: the (trainer, compiled, report) of the config's
  own setting if already compiled. :class:`DoesNotFitError` naming the smallest setting tried and
  its size when none fits."""
  limit = _limit(target, budget_bytes)
  batch = batch or config.batch_size
  mesh = parallel.make_mesh(tuple(config.mesh), list(target.devices))
  tried = []
  for i, (remat, accum) in enumerate(fit_ladder(config, batch,
                                                mesh.shape["data"] * mesh.shape["fsdp"])):
    candidate = with_setting(config, remat, accum)
    trainer, _, report = (first if i == 0 and first is not None else
                          compile_step(candidate, target, batch, limit))
    tried.append({"remat": remat, "grad_accum": accum, "total_gib": report["total_gib"]})
    log(f"fit: {describe(report)}")
    if report["fits"]:
      report["tried"] = tried
      return candidate, trainer, report
  smallest = min(tried, key=lambda t: float("inf") if t["total_gib"] is None else t["total_gib"])
  raise DoesNotFitError(
      f"no setting fits {limit / GIB:.3g} GiB per device on {target.spec}: the smallest tried, "
      f"remat={smallest['remat']} grad_accum={smallest['grad_accum']}, needs "
      f"{_gib(smallest['total_gib'])} GiB; use more devices (FSDP: the mesh's fsdp axis), a "
      f"smaller batch or a smaller model")


def fit_train(config: ml_collections.ConfigDict, target: Target, budget_bytes: int | None = None,
              batch: int | None = None, log=print) -> tuple[ml_collections.ConfigDict, dict]:
  """(fitted config, report) of :func:`fit_step`."""
  fitted, _, report = fit_step(config, target, budget_bytes, batch, log=log)
  return fitted, report


def fit_for_training(config: ml_collections.ConfigDict, log=print
                     ) -> tuple[ml_collections.ConfigDict, ShardedTrainer, dict]:
  """Before the first step: compile the step on this process's devices, compare it with the
  device's limit (the allocator's ``bytes_limit`` on GPU / TPU, ``train.memory_budget_gib`` when
  set and on CPU) and, with ``train.auto_fit``, climb :func:`fit_ladder` until it fits ->
  (config as trained, trainer with the step compiled, report). Without a known limit (CPU and no
  budget) the config is kept as it is. :class:`DoesNotFitError` when the step cannot fit."""
  budget = config.train.memory_budget_gib
  target = parse_target("local")
  limit = int(budget * GIB) if budget else usable_memory(target)
  first = compile_step(config, target, budget_bytes=limit)
  report = first[2]
  if report["fits"] is None or report["fits"]:
    log(f"compiled step: {describe(report)}"
        + ("; no memory limit known here (set train.memory_budget_gib to check one)"
           if report["fits"] is None else ""))
    return config, first[0], report
  if not config.train.auto_fit:
    raise DoesNotFitError(f"the compiled step does not fit: {describe(report)}; set "
                          f"train.auto_fit=True to choose remat and gradient accumulation, or "
                          f"lower batch_size")
  fitted, trainer, report = fit_step(config, target, limit, first=first, log=log)
  log(f"auto_fit chose model.remat={report['remat']!r} optim.grad_accum={report['grad_accum']}: "
      f"{report['total_gib']:.3g} GiB per device of {report['limit_gib']:.3g} (the config's "
      f"remat={config.model.remat!r} grad_accum={config.optim.grad_accum} needs "
      f"{_gib(first[2]['total_gib'])})")
  return fitted, trainer, report


def compile_report(config: ml_collections.ConfigDict, target: Target, what: str = "train",
                   batch: int | None = None, budget_bytes: int | None = None, log=print) -> dict:
  """The report of :func:`compile_step` (``what='train'``) or :func:`compile_rollout`
  (``'rollout'``) for ``target``. A train step that does not fit also gets ``auto_fit``: the
  setting :func:`fit_step` would choose (remat, grad_accum, its size and what was tried)."""
  if what == "rollout":
    return compile_rollout(config, target, batch, budget_bytes)
  first = compile_step(config, target, batch, budget_bytes)
  report = first[2]
  if report["fits"] is False:
    _, _, chosen = fit_step(config, target, budget_bytes, batch, first=first, log=log)
    report["auto_fit"] = {"remat": chosen["remat"], "grad_accum": chosen["grad_accum"],
                          "total_gib": chosen["total_gib"], "tried": chosen["tried"]}
  return report
