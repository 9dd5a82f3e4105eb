"""Fits before it runs: compiled memory for a device target, the auto-fit ladder, activation
sharding under FSDP, and commands that keep JAX off accelerators."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from conftest import ROOT, tiny_config
from wmjax.config import load_config
from wmjax.train import aot, fit
from wmjax.train.context import build_context, compile_step, fit_context, fit_to_memory
from wmjax.train.step import ShardedTrainer

# A small gridworld model: 8x8 RGB frames, 4-frame windows, global batch 16 on 8 devices.
SMALL = ("model.in_channels=3", "model.action_dim=4", "model.hidden_size=32", "model.num_heads=2",
         "model.num_frames=4", "data.frames=4", "frame_shape=(8, 8, 3)", "batch_size=16",
         "model.remat='full'")


def _batch(seed=0, batch=16):
  k1, k2 = jax.random.split(jax.random.key(seed))
  return (jax.random.uniform(k1, (batch, 4, 8, 8, 3), minval=-1, maxval=1),
          jax.random.normal(k2, (batch, 3, 4)))


@pytest.mark.integration
@pytest.mark.slow
def test_auto_fit_takes_micro_batches_under_a_budget_and_keeps_the_loss():
  """Under a memory budget below the plain step's compiled size, the trainer's fit climbs to
  gradient accumulation, says so, and its first step has the plain step's loss."""
  config = tiny_config("gridworld.py", *SMALL)
  local = fit.parse_target("local")
  plain_context = build_context(config, local)
  _, plain = compile_step(plain_context)
  assert plain["fits"] is None and plain["grad_accum"] == 1  # CPU: no limit without a budget
  # a step that fits (no limit known) trains with the context it was set up with: one trainer
  assert fit_to_memory(plain_context, log=lambda line: None)[0] is plain_context
  budget = 0.9 * plain["total_gib"]
  tight = build_context(tiny_config("gridworld.py", *SMALL, f"train.memory_budget_gib={budget}"),
                        local)
  lines = []
  fitted, report = fit_to_memory(tight, log=lines.append)
  assert report["grad_accum"] > 1 and fitted.config.optim.grad_accum == report["grad_accum"]
  # the fitted trainer runs on the context's one mesh, with the context's model at its remat
  assert fitted.trainer.mesh is tight.mesh and fitted.mesh is tight.mesh
  assert fitted.world_model.network.remat == report["remat"] == fitted.config.model.remat
  assert report["fits"] and report["total_gib"] <= budget < plain["total_gib"]
  assert [t["grad_accum"] for t in report["tried"]][0] == 1
  assert any("auto_fit chose" in line and f"grad_accum={report['grad_accum']}" in line
             for line in lines)
  losses = []
  for t in (plain_context.trainer, fitted.trainer):
    _, metrics = t.step(t.init(jax.random.key(0)), *_batch())
    losses.append(float(metrics["loss"]))
  np.testing.assert_allclose(losses[1], losses[0], rtol=1e-5)


def _sized_measure(gib_of):
  """A stand-in for the compiled step's measure: ``gib_of(remat, grad_accum)`` GiB per device,
  fitting the budget or not, and the settings it was asked for."""
  asked = []

  def measure(remat, grad_accum, budget_bytes):
    asked.append((remat, grad_accum))
    total = gib_of(remat, grad_accum)
    return (remat, grad_accum), {
        "what": "train", "target": "cpu:2", "batch": 16, "remat": remat, "grad_accum": grad_accum,
        "total_gib": total, "arguments_gib": 0.0, "temp_gib": total,
        "limit_gib": budget_bytes / fit.GIB, "fits": total * fit.GIB <= budget_bytes}
  return measure, asked


@pytest.mark.unit
def test_a_step_that_does_not_fit_stops_with_the_setting_to_change():
  """Without train.auto_fit the config's own setting is the only one tried, and the error says
  what to set; when no setting of the ladder fits, the error names the smallest tried."""
  target = fit.parse_target("cpu:2")
  config = tiny_config("gridworld.py", *SMALL, "train.memory_budget_gib=1.0", "train.auto_fit=False")
  measure, asked = _sized_measure(lambda remat, accum: 2.0)
  with pytest.raises(fit.DoesNotFitError, match=r"does not fit.*train.auto_fit=True"):
    fit.fit_for_training(config, target, measure, 2, log=lambda line: None)
  assert asked == [("full", 1)]
  measure, asked = _sized_measure(lambda remat, accum: 2.0 + 1.0 / accum)
  with pytest.raises(fit.DoesNotFitError, match=r"no setting fits 1 GiB per device on cpu:2: the "
                     r"smallest tried, remat=full grad_accum=(\d+), needs 2\.\d+ GiB") as error:
    fit.fit_step(config, target, measure, 2, fit.GIB, log=lambda line: None)
  assert len(asked) > 1 and f"grad_accum={max(a for _, a in asked)}," in str(error.value)


@pytest.mark.unit
def test_auto_fit_takes_the_setting_predicted_fastest_of_those_that_fit():
  """IRASim-XL/2's step at batch 16 as compiled for an H100 (GiB per device; predicted ms from
  the H200-calibrated cost model): no remat fits only over two micro-batches, dots_elementwise not
  at all with one, dots with one. The search skips what cannot pay (full remat at one
  micro-batch recomputes more than dots) and takes the fastest that fits, not the first."""
  target = fit.parse_target("cpu:2")
  config = tiny_config("gridworld.py", *SMALL, "model.remat='none'")
  sizes = {("none", 1): (131.0, 520.0), ("none", 2): (60.3, 627.0),
           ("dots_elementwise", 1): (93.1, 600.0), ("dots", 1): (60.2, 669.0),
           ("full", 1): (24.0, 900.0)}

  def measure(remat, accum, budget_bytes):
    asked.append((remat, accum))
    total, ms = sizes.get((remat, accum), (10.0 + 121.0 / accum, 520.0 + 100 * accum))
    return (remat, accum), {"what": "train", "target": "h100", "batch": 16, "remat": remat,
                            "grad_accum": accum, "total_gib": total, "arguments_gib": 10.0,
                            "temp_gib": total - 10.0,
                            "limit_gib": budget_bytes / fit.GIB, "predicted_ms": ms,
                            "fits": total * fit.GIB <= budget_bytes}

  asked = []
  lines = []
  _, report = fit.fit_step(config, target, measure, 1, int(75.1 * fit.GIB), log=lines.append)
  assert (report["remat"], report["grad_accum"]) == ("none", 2)
  assert asked == [("none", 1), ("none", 2), ("dots_elementwise", 1), ("dots", 1)]
  assert [t["fits"] for t in report["tried"]] == [False, True, False, True]
  assert "fits, predicted 627 ms a step" in lines[1]
  sizes["dots", 1] = (60.2, 600.0)  # were dots the faster, it would be taken
  asked = []
  _, report = fit.fit_step(config, target, measure, 1, int(75.1 * fit.GIB), log=lines.append)
  assert (report["remat"], report["grad_accum"]) == ("dots", 1)


@pytest.mark.unit
def test_the_cost_model_prices_the_steps_measured_on_an_h200():
  """The package's efficiencies predict each IRASim-XL/2 step measured on one H200 (remat and
  layer settings; their costs read off the steps' HLO by benchmarks/cost_model.py) within 5 %, and
  order every two steps that differ by more than that as measured."""
  measured = json.loads((ROOT / "benchmarks/results/h200/cost_model.json").read_text())
  rates = fit.DEVICE_RATES[measured["rates"]]
  points = [(p["step_ms"], 1e3 * fit.predicted_step_s(p["cost"], rates))
            for p in measured["points"]]
  assert len(points) >= 5
  for step_ms, predicted_ms in points:
    assert predicted_ms == pytest.approx(step_ms, rel=0.05)
  for a, b in ((a, b) for a in points for b in points if a[0] < 0.95 * b[0]):
    assert a[1] < b[1]


REFUSAL = ("RESOURCE_EXHAUSTED: Ran out of memory on HBM, the total memory required for HLO "
           "temporaries (123.37G) exceeds available HBM (95.74G).")


@pytest.mark.integration
@pytest.mark.slow
def test_a_step_the_compiler_refuses_does_not_fit_and_the_ladder_climbs(monkeypatch):
  """A TPU compiler refuses a program larger than the HBM (RESOURCE_EXHAUSTED) instead of
  reporting its size: that setting does not fit, and the ladder goes on to the next one."""
  original = ShardedTrainer.compile

  def compile_refusing_no_remat(trainer, *args):
    if trainer.world_model.network.remat == "none":
      raise jax.errors.JaxRuntimeError(REFUSAL)
    return original(trainer, *args)

  monkeypatch.setattr(ShardedTrainer, "compile", compile_refusing_no_remat)
  config = tiny_config("gridworld.py", *SMALL, "model.remat='none'")
  lines = []
  fitted, report = fit_context(build_context(config, fit.parse_target("cpu:2")),
                               budget_bytes=fit.GIB, batch=2, log=lines.append)
  assert fitted.config.model.remat == "dots_elementwise" and report["fits"]
  assert report["tried"][0] == {"remat": "none", "grad_accum": 1, "total_gib": 123.37,
                                "fits": False, "predicted_ms": None}
  assert "more than 123 GiB per device, refused by the compiler" in lines[0]
  assert fit.refused_report(jax.errors.JaxRuntimeError("INTERNAL: boom"),
                            fit.parse_target("cpu:2")) is None


@pytest.mark.unit
def test_targets_parse_and_refuse_clearly():
  assert len(fit.parse_target("cpu:2").devices) == 2
  with pytest.raises(ValueError, match="unknown compile target 'k80'"):
    fit.parse_target("k80")
  with pytest.raises(ValueError, match="positive integer"):
    fit.parse_target("h100:0")
  with pytest.raises(ValueError, match="needs 64 CPU devices"):
    fit.parse_target("cpu:64")
  assert fit.remat_ladder("none") == ("none", "dots_elementwise", "dots", "full")
  assert fit.remat_ladder("dots_attention") == ("dots_attention", "dots", "full")
  assert fit.accumulations(1, 16, 8) == [1, 2] and fit.accumulations(2, 8, 2) == [2, 4]
  assert fit.device_rates(fit.parse_target("cpu:2")) is None


@pytest.mark.integration
@pytest.mark.slow
def test_rollout_block_compiles_for_a_target_with_its_memory():
  """``wmjax compile --what rollout``: one rollout block jitted for the target's first device, its
  memory against a budget, the sampler's model calls and the analytic FLOPs."""
  config = tiny_config("gridworld.py", *SMALL, "rollout.horizon=3")
  report = aot.compile_report(config, fit.parse_target("cpu:2"), "rollout", 2,
                              budget_bytes=fit.GIB)
  assert report["what"] == "rollout" and report["devices"] == 1 and report["batch"] == 2
  assert (report["context"], report["horizon"]) == (1, 3) and report["model_calls"] > 0
  assert report["fits"] and 0 < report["arguments_gib"] < report["total_gib"] < 1
  assert report["analytic_flops"] > 0
  assert report["hlo_cost"]["matmul_flops"] > 0 and report["predicted_ms"] is None  # CPU rates
  assert "rollout on cpu:2 (batch 2," in fit.describe(report)


@pytest.mark.integration
@pytest.mark.skipif(sys.platform != "linux", reason="libtpu (the [tpu] extra) is Linux-only")
@pytest.mark.slow
def test_train_step_compiles_for_a_tpu_pod_slice_without_one():
  """A v5p:2x2x1 topology (4 chips, from libtpu on this CPU machine): the sharded step compiles
  for the TPU, attention resolves to the TPU's splash kernel, and the memory is the TPU's."""
  pytest.importorskip("libtpu", reason="compiling for a TPU topology needs the tpu extra")
  config = tiny_config("gridworld.py", *SMALL, "model.attention_impl='auto'", "mesh=(1, -1, 1)")
  target = fit.parse_target("v5p:2x2x1")
  assert target.platform == "tpu" and len(target.devices) == 4
  report = aot.compile_train(config, target)
  assert report["mesh"] == {"data": 1, "fsdp": 4, "tensor": 1}
  assert report["attention"] == "splash"
  assert report["device_memory_gib"] == 95 and report["fits"]
  assert 0 < report["arguments_gib"] < report["total_gib"]
  assert report["xla_flops_per_device"] > 0
  # its matmuls (convolutions on a TPU) are priced at the TPU's rates
  assert report["hlo_cost"]["matmul_flops"] > report["xla_flops_per_device"]
  assert report["predicted_ms"] > 0


@pytest.mark.integration
@pytest.mark.slow
def test_fsdp_activation_memory_stays_with_the_data_parallel_step():
  """With activations constrained to the batch axes, FSDP over 4 devices needs no more temporary
  memory than data parallelism over 4 (same per-device batch) plus one layer's gathered weights.
  (Without the constraints this step's FSDP temp memory was 2.9x the data-parallel one.)"""
  d = 128
  overrides = ("model.depth=2", f"model.hidden_size={d}", "model.num_heads=4",
               "model.num_frames=8", "data.frames=8", "model.remat='dots'")
  target = fit.parse_target("cpu:4")
  temps = {}
  for name, mesh in (("dp", "(4, 1, 1)"), ("fsdp", "(1, 4, 1)")):
    config = load_config(str(ROOT / "configs" / "irasim.py:S"), overrides + (f"mesh={mesh}",))
    temps[name] = aot.compile_train(config, target, batch=8)["temp_gib"]
  layer_weights = 2 * 18 * d * d * 4 / fit.GIB  # spatial + temporal block (attention 4D^2, MLP
  assert temps["fsdp"] <= temps["dp"] + layer_weights, temps  # 8D^2, adaLN 6D^2), float32


def _run_host_only(command: list[str]) -> dict:
  """Run ``wmjax COMMAND`` in a fresh process whose environment asks for a CUDA backend; return
  the JAX backends it initialised."""
  script = ("import json, sys; from jax._src import xla_bridge; from wmjax.cli import main; "
            "code = main(sys.argv[1:]); "
            "print('BACKENDS=' + json.dumps(sorted(xla_bridge._backends))); sys.exit(code)")
  env = dict(os.environ, JAX_PLATFORMS="cuda",
             PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
  # the command sets its own host device count (compile --target cpu:N); the suite's compiler
  # flags stay, so that its compile is as quick as the suite's
  env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split()
                              if not f.startswith("--xla_force_host_platform_device_count"))
  done = subprocess.run([sys.executable, "-c", script] + command, cwd=ROOT, env=env,
                        capture_output=True, text=True, timeout=600)
  assert done.returncode == 0, done.stderr[-2000:]
  line = [row for row in done.stdout.splitlines() if row.startswith("BACKENDS=")][-1]
  return {"backends": json.loads(line.removeprefix("BACKENDS=")), "stdout": done.stdout}


@pytest.mark.integration
@pytest.mark.slow
def test_host_commands_never_start_an_accelerator_backend(tmp_path):
  """info and compile run on the CPU even where JAX_PLATFORMS asks for a GPU (a GPU backend would
  fail here, or take 75 % of the card where there is one); compile --target cpu:2 gets its two
  host devices and writes its JSON."""
  small = [f"--config.{o}" for o in SMALL]
  info = _run_host_only(["info", "--config", "configs/gridworld.py"])
  assert info["backends"] == ["cpu"]
  out = tmp_path / "report.json"
  compiled = _run_host_only(["compile", "--config", "configs/gridworld.py", "--target", "cpu:2",
                             "--budget_gib", "1", "--out", str(out)] + small)
  assert compiled["backends"] == ["cpu"]
  report = json.loads(out.read_text())
  assert report["devices"] == 2 and report["mesh"]["data"] == 2 and report["fits"]
  assert "train on cpu:2 (batch 16, remat=full grad_accum=1)" in compiled["stdout"]
