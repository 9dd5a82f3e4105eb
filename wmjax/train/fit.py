"""Device targets, the memory a compiled program needs on one of them, and the choice of remat and
gradient accumulation that makes a train step fit.

A target is a set of devices to compile for, with or without their hardware; XLA's memory
analysis of a program compiled for it says what one device needs (arguments, outputs,
temporaries). Targets:

``cpu:N``          N host devices (simulated: ``jax_num_cpu_devices``)
``h100[:N]``       N H100 80GB; ``h200[:N]`` (141 GB), ``a100[:N]`` (A100 80GB) — compiled on any
                   machine where JAX's CUDA plugin is installed (no GPU needed)
``v5p:2x2x1`` ...  a Cloud TPU topology (``v4``, ``v5e``, ``v5p``, ``v6e``); needs libtpu
``local``          the devices this process sees (what the trainer uses)

:func:`fit_step` searches remat (none -> dots_elementwise -> dots -> full) and gradient-
accumulation micro-batches (the config's, doubled as the batch allows) from the config's own: for
each remat the fewest micro-batches whose compiled step fits the device's memory, a heavier remat
only where it needs fewer micro-batches. Of the settings that fit it takes the one
:func:`predicted_step_s` prices fastest (matmul FLOPs and the bytes every other kernel moves,
read off the compiled step's optimized HLO by :mod:`wmjax.train.hlo_cost`, over the device's
rates), and says what it chose and what it tried. It only chooses: the step of each setting is
built and compiled by the caller (:mod:`wmjax.train.context`, which builds the mesh, the model
and the trainer of a run in one place).
"""

from __future__ import annotations

import dataclasses
import os
import re
from typing import Any, Callable, Union

import jax
import ml_collections

from wmjax.errors import RunError
from wmjax.train import hlo_cost

GIB = 1024 ** 3
# What a layer keeps, least recomputation first (wmjax.nn.dit.REMAT_POLICIES). 'dots_attention'
# is left out: on one H200 it ran no faster than 'dots' and took 4.7 GiB more (IRASim-XL/2,
# benchmarks/RESULTS.md, 2026-11-30). A policy off the ladder starts it at the next one that
# keeps less.
REMAT_LADDER = ("none", "dots_elementwise", "dots", "full")
_OFF_LADDER = {"dots_attention": "dots", "dots_all": "dots"}
# One device's dense bf16 FLOP/s and memory bandwidth (bytes/s), from the vendors' datasheets.
DEVICE_RATES = {"h100": (989e12, 3.35e12), "h200": (989e12, 4.8e12), "a100": (312e12, 2.039e12),
                "v4": (275e12, 1.2e12), "v5e": (197e12, 8.19e11), "v5litepod": (197e12, 8.19e11),
                "v5p": (459e12, 2.765e12), "v6e": (918e12, 1.64e12)}
# Fragments of a local device's device_kind (lower case), first match, to its DEVICE_RATES name.
_DEVICE_KINDS = (("h200", "h200"), ("h100", "h100"), ("a100", "a100"), ("v6", "v6e"),
                 ("v5 lite", "v5e"), ("v5e", "v5e"), ("v5", "v5p"), ("v4", "v4"))
# The fractions of those rates a train step reaches: fitted to five IRASim-XL/2 train steps (remat
# and layer settings) measured on one H200, each predicted within 3.4 % (benchmarks/cost_model.py,
# benchmarks/RESULTS.md, 2026-11-30). Not calibrated on other cards or on TPUs.
MATMUL_EFFICIENCY = 0.54
BANDWIDTH_EFFICIENCY = 0.80
# cuBLAS float8 GEMMs run at twice the dense bf16 peak on every card XLA emits them for (Ada,
# Hopper, Blackwell datasheets); priced at the same MATMUL_EFFICIENCY of that peak, which no card
# measurement has checked yet.
FLOAT8_SPEEDUP = 2.0


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
      raise ValueError(f"target {spec!r} needs libtpu (pip install -e \".[tpu]\" or 'jax[tpu]=="
                       f"{jax.__version__}'; no TPU needed) and a valid topology: {e}") from e
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


def remat_ladder(remat: str) -> tuple[str, ...]:
  """The remat policies :func:`fit_step` tries from ``remat`` on: ``remat`` itself, then the
  ladder's policies that keep less."""
  if remat in REMAT_LADDER:
    return REMAT_LADDER[REMAT_LADDER.index(remat):]
  return (remat,) + REMAT_LADDER[REMAT_LADDER.index(_OFF_LADDER.get(remat, "none")):]


def accumulations(start: int, batch: int, data_parallel: int) -> list[int]:
  """Micro-batch counts :func:`fit_step` tries: ``start``, then doubling as long as every device
  keeps at least one sample of each micro-batch of the global ``batch``."""
  counts, k = [start], start * 2
  while batch % (data_parallel * k) == 0:
    counts.append(k)
    k *= 2
  return counts


def device_rates(target: Target) -> tuple[float, float] | None:
  """(FLOP/s, bytes/s) of one device of ``target`` (:data:`DEVICE_RATES`); None where unknown
  (CPUs, other cards)."""
  name = target.spec.partition(":")[0].lower()
  if name == "local" and target.platform != "cpu":
    kind = target.devices[0].device_kind.lower()
    name = next((rates for fragment, rates in _DEVICE_KINDS if fragment in kind), name)
  return DEVICE_RATES.get(name)


def predicted_step_s(cost: dict, rates: tuple[float, float]) -> float:
  """Seconds one execution of a compiled step takes on a device of ``rates`` (FLOP/s, bytes/s),
  by its ``cost`` (:func:`wmjax.train.hlo_cost.step_cost`): its matmul FLOPs at
  :data:`MATMUL_EFFICIENCY` of the peak (:data:`FLOAT8_SPEEDUP` times it for float8 GEMMs) plus
  the bytes its other kernels move at :data:`BANDWIDTH_EFFICIENCY` of the bandwidth."""
  flops, bandwidth = rates
  fp8 = cost.get("fp8_matmul_flops", 0.0)
  matmul_flops = cost["matmul_flops"] - fp8 + fp8 / FLOAT8_SPEEDUP
  return (matmul_flops / (MATMUL_EFFICIENCY * flops)
          + cost["other_bytes"] / (BANDWIDTH_EFFICIENCY * bandwidth))


def cost_report(compiled: jax.stages.Compiled, target: Target) -> dict:
  """What one execution of ``compiled`` does (``hlo_cost``: :func:`wmjax.train.hlo_cost.step_cost`)
  and the milliseconds :func:`predicted_step_s` gives it on ``target`` (``predicted_ms``; None
  where the target's rates are unknown)."""
  cost = hlo_cost.step_cost(compiled.as_text())
  rates = device_rates(target)
  return {"hlo_cost": cost,
          "predicted_ms": None if rates is None else 1e3 * predicted_step_s(cost, rates)}


def _next_count(report: dict, counts: list[int], i: int, limit: int) -> int:
  """Index into ``counts`` of the fewest micro-batches after ``counts[i]`` whose step could fit
  ``limit`` bytes, its temporaries taken to shrink as 1 / micro-batches (they shrink less: the
  gradients stay, so no count that could fit is skipped); ``len(counts)`` when none can."""
  temp, total = report.get("temp_gib"), report.get("total_gib")
  if temp is None or total is None:
    return i + 1
  state = total - temp  # arguments and outputs: the train state
  return next((j for j in range(i + 1, len(counts))
               if (state + temp * counts[i] / counts[j]) * GIB <= limit), len(counts))


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
  if report.get("predicted_ms") is not None:
    verdict += (f", predicted {report['predicted_ms']:.0f} ms a "
                f"{'step' if report['what'] == 'train' else 'block'}")
  head = f"{report['what']} on {report['target']} (batch {report['batch']}, {setting}): "
  if report.get("refused"):
    return (f"{head}more than {_gib(report['temp_gib'])} GiB per device, refused by the "
            f"compiler{verdict} ({report['refused']})")
  return (f"{head}{report['total_gib']:.3g} GiB per device (arguments "
          f"{report['arguments_gib']:.3g} + temp {report['temp_gib']:.3g}){verdict}")


def _gib(value: float | None) -> str:
  return "an unknown number of" if value is None else f"{value:.3g}"


# measure(remat, grad_accum, budget_bytes) -> (what it built, its report): the step of that
# setting compiled, and whether it fits budget_bytes
Measure = Callable[[str, int, Union[int, None]], tuple[Any, dict]]


def fit_step(config: ml_collections.ConfigDict, target: Target, measure: Measure,
             data_parallel: int, budget_bytes: int | None = None, batch: int | None = None,
             first: tuple[Any, dict] | None = None, log=print) -> tuple[Any, dict]:
  """The setting whose step, as ``measure`` compiles it, fits ``budget_bytes`` (default: what the
  target's allocator may take) and is predicted fastest (``predicted_ms`` of its report; where
  the target's rates are unknown, the first found) -> (what ``measure`` built for it, its report
  with ``tried``). For each policy of :func:`remat_ladder` from the config's own, the fewest
  micro-batches of :func:`accumulations` that fit (a step that does not fit says by its
  temporaries how many more to try); a policy that keeps less is tried only with fewer
  micro-batches than one that keeps more needed, since with as many it only recomputes more.
  ``data_parallel``: the devices the global ``batch`` (default ``config.batch_size``) is split
  over; ``first``: the (built, report) of the config's own setting if already compiled.
  :class:`DoesNotFitError` naming the smallest setting tried and its size when none fits."""
  limit = _limit(target, budget_bytes)
  counts = accumulations(config.optim.grad_accum, batch or config.batch_size, data_parallel)
  own = (config.model.remat, config.optim.grad_accum)
  tried, fitting = [], []
  bound = len(counts)  # only fewer micro-batches than this index can pay for more recomputation
  for remat in remat_ladder(config.model.remat):
    i = 0
    while i < bound:
      setting = (remat, counts[i])
      built, report = (first if setting == own and first is not None
                       else measure(remat, counts[i], budget_bytes))
      tried.append({"remat": remat, "grad_accum": counts[i], "total_gib": report["total_gib"],
                    "fits": report["fits"], "predicted_ms": report.get("predicted_ms")})
      log(f"fit: {describe(report)}")
      if report["fits"]:
        fitting.append((built, report))
        bound = i
        break
      i = _next_count(report, counts, i, limit)
    if bound == 0:
      break
  if not fitting:
    smallest = min(tried,
                   key=lambda t: float("inf") if t["total_gib"] is None else t["total_gib"])
    raise DoesNotFitError(
        f"no setting fits {limit / GIB:.3g} GiB per device on {target.spec}: the smallest tried, "
        f"remat={smallest['remat']} grad_accum={smallest['grad_accum']}, needs "
        f"{_gib(smallest['total_gib'])} GiB; use more devices (FSDP: the mesh's fsdp axis), a "
        f"smaller batch or a smaller model")
  priced = [f for f in fitting if f[1].get("predicted_ms") is not None]
  built, report = min(priced, key=lambda f: f[1]["predicted_ms"]) if priced else fitting[0]
  report["tried"] = tried
  return built, report


def training_budget(config: ml_collections.ConfigDict, target: Target) -> int | None:
  """Bytes the train step may take on one device of ``target``: ``train.memory_budget_gib`` when
  set, else what the allocator may take (None where unknown: the host CPU)."""
  budget = config.train.memory_budget_gib
  return int(budget * GIB) if budget else usable_memory(target)


def fit_for_training(config: ml_collections.ConfigDict, target: Target, measure: Measure,
                     data_parallel: int, log=print) -> tuple[Any, dict]:
  """Before the first step: the config's own setting, as ``measure`` compiles it against
  :func:`training_budget`, when it fits or no limit is known (the host CPU without a budget);
  else, with ``train.auto_fit``, the setting :func:`fit_step` chooses (of those that fit, the one
  predicted fastest) -> (what ``measure`` built, its report). :class:`DoesNotFitError` when the
  step cannot fit."""
  budget = training_budget(config, target)
  first = measure(config.model.remat, config.optim.grad_accum, budget)
  report = first[1]
  if report["fits"] is None or report["fits"]:
    log(f"compiled step: {describe(report)}"
        + ("; no memory limit known here (set train.memory_budget_gib to check one)"
           if report["fits"] is None else ""))
    return first
  if not config.train.auto_fit:
    raise DoesNotFitError(f"the compiled step does not fit: {describe(report)}; set "
                          f"train.auto_fit=True to choose remat and gradient accumulation, or "
                          f"lower batch_size")
  built, chosen = fit_step(config, target, measure, data_parallel, budget, first=first, log=log)
  fitting = sum(1 for t in chosen["tried"] if t["fits"])
  speed = ("" if chosen.get("predicted_ms") is None else
           f", predicted {chosen['predicted_ms']:.0f} ms a step, the fastest of {fitting} that fit")
  log(f"auto_fit chose model.remat={chosen['remat']!r} optim.grad_accum={chosen['grad_accum']}: "
      f"{chosen['total_gib']:.3g} GiB per device of {chosen['limit_gib']:.3g}{speed} (the config's "
      f"remat={config.model.remat!r} grad_accum={config.optim.grad_accum} needs "
      f"{_gib(report['total_gib'])})")
  return built, chosen
