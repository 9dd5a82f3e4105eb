"""The training loop end to end: kill and resume, two processes, NaN, early errors (SIGTERM and
Ctrl-C: test_run_integrity.py)."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from conftest import ROOT, gridworld_overrides, tiny_config
from wmjax.launch import launch_local, process_env
from wmjax.train.loop import NonFiniteLossError, train
from wmjax.train.step import ShardedTrainer

pytestmark = pytest.mark.integration


def _overrides(data_dir, **extra):
  """The suite's tiny gridworld run (conftest.py), at batch 4 for 8 steps."""
  return gridworld_overrides(data_dir, **{"batch_size": 4, "train.num_steps": 8,
                                          "optim.warmup_steps": 2, "optim.total_steps": 8,
                                          **extra})


def _env(devices=2):
  env = process_env(0, "cpu", devices)  # the launcher's: the suite's XLA flags, `devices` devices
  env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
  return env


def _train_command(workdir, overrides):
  return [sys.executable, "-m", "wmjax.cli", "train", "--config", "configs/gridworld.py",
          "--workdir", str(workdir)] + [f"--config.{o}" for o in overrides]


def _state(workdir, step):
  return ocp.PyTreeCheckpointer().restore(os.path.join(workdir, "checkpoints", str(step), "state"))


def _batches(workdir):
  """step -> batch fingerprint, checking that a step logged twice saw the same batch."""
  seen = {}
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    for line in f:
      record = json.loads(line)
      assert seen.setdefault(record["step"], record["batch"]) == record["batch"]
  return seen


@pytest.mark.slow
def test_kill_and_resume_is_bit_identical_and_another_slice_size_reads_the_same_batches(
    data_dir, tmp_path):
  """A run over 8 devices (FSDP) killed after a checkpoint and resumed on the same mesh ends
  bit-identical to an uninterrupted run. The same checkpoint resumed over 4 devices (a preempted
  job on a smaller slice: another mesh) reads the batches the uninterrupted run reads, step by
  step, and ends where that run ends but for the reduction order."""
  overrides = _overrides(data_dir, batch_size=8)
  eight, four = overrides + ["mesh=(1, 8, 1)"], overrides + ["mesh=(1, 4, 1)"]
  straight, killed, moved = tmp_path / "straight", tmp_path / "killed", tmp_path / "moved"
  # each pair of runs goes side by side: each spends most of its time importing and compiling
  # on one core
  uninterrupted = subprocess.Popen(_train_command(straight, eight), cwd=ROOT, env=_env(8),
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
  process = subprocess.Popen(_train_command(killed, eight), cwd=ROOT, env=_env(8),
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
  checkpoints = killed / "checkpoints"
  deadline = time.time() + 300
  while not any((checkpoints / str(s)).is_dir() for s in (4, 6)):
    assert process.poll() is None and time.time() < deadline, "no checkpoint before the deadline"
    time.sleep(0.05)
  process.send_signal(signal.SIGKILL)
  process.wait()
  assert not (checkpoints / "8").exists()
  shutil.copytree(killed, moved)
  resumed = {workdir: subprocess.Popen(_train_command(workdir, command), cwd=ROOT, env=_env(n),
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for workdir, command, n in ((killed, eight, 8), (moved, four, 4))}
  outputs = {workdir: run.communicate(timeout=300) for workdir, run in resumed.items()}
  for workdir, run in resumed.items():
    assert run.returncode == 0, outputs[workdir][1][-3000:]
    assert "resumed from step" in outputs[workdir][0]
  out, err = outputs[killed]
  # to a pipe, not a terminal: one plain progress line per log, no carriage-return bar
  assert "step 8/8: loss " in out and "ETA 0:00" in out
  assert "\r" not in err and "train:" not in err
  assert json.loads((moved / "config.json").read_text())["mesh"] == [1, 4, 1]
  _, errors = uninterrupted.communicate(timeout=300)
  assert uninterrupted.returncode == 0, errors[-3000:]

  a, b, c = (_flatten(_state(workdir, 8)) for workdir in (straight, killed, moved))
  assert a.keys() == b.keys() == c.keys() and len(a) > 10
  for key in a:
    np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    np.testing.assert_allclose(c[key], a[key], rtol=1e-4, atol=1e-6, err_msg=key)
  assert _batches(straight) == _batches(killed) == _batches(moved)
  assert sorted(_batches(straight)) == list(range(1, 9))
  losses = [{r["step"]: r["loss"] for r in map(json.loads, open(w / "metrics.jsonl"))}
            for w in (straight, moved)]
  for step in range(1, 9):
    np.testing.assert_allclose(losses[1][step], losses[0][step], rtol=1e-5, err_msg=step)
  # train.eval_every=0: no evaluation at all, not even at the end
  assert json.loads((straight / "metrics.json").read_text()) == {"step": 8}
  assert not (straight / "rollout.gif").exists() and not (straight / "samples").exists()


def _flatten(tree):
  return {jax.tree_util.keystr(path): np.asarray(leaf)
          for path, leaf in jax.tree_util.tree_leaves_with_path(tree)}


@pytest.mark.slow
def test_local_launcher_runs_two_cooperating_processes(data_dir, tmp_path, capfd, monkeypatch):
  """`wmjax.launch` starts a 2-process CPU training job (one device each): both finish, hold the
  same parameters, and the checkpoint is written."""
  overrides = _overrides(data_dir, **{"train.num_steps": 3, "train.checkpoint_every": 3})
  monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
  monkeypatch.chdir(ROOT)
  code = launch_local([sys.executable, str(ROOT / "tests" / "distributed_worker.py"),
                       str(tmp_path / "run")] + overrides, 2, timeout=600)
  output = capfd.readouterr().out
  assert code == 0, output[-6000:]
  digests = [line.split() for line in output.splitlines() if "DIGEST" in line]
  assert sorted(d[0] for d in digests) == ["[0]", "[1]"] and all(d[3] == "2" for d in digests)
  assert digests[0][4] == digests[1][4]
  assert (tmp_path / "run" / "checkpoints" / "3").is_dir()


def test_launcher_stops_every_process_when_one_fails(tmp_path):
  script = tmp_path / "fail.py"
  script.write_text("import sys, time\n"
                    "index = int(sys.argv[sys.argv.index('--process_id') + 1])\n"
                    "sys.exit(3) if index == 1 else time.sleep(120)\n")
  start = time.time()
  assert launch_local([sys.executable, str(script)], 2, timeout=100) == 3
  assert time.time() - start < 60


@pytest.mark.slow
def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(data_dir, tmp_path, monkeypatch):
  """From step 4 on the step returns NaN parameters and loss (as a diverged run would)."""
  real_step = ShardedTrainer.step

  def diverging_step(self, state, frames, actions):
    state, metrics = real_step(self, state, frames, actions)
    if int(state.step) >= 4:
      state = state.replace(params=jax.tree.map(lambda p: p * jnp.nan, state.params))
      metrics = dict(metrics, loss=metrics["loss"] * jnp.nan)
    return state, metrics

  monkeypatch.setattr(ShardedTrainer, "step", diverging_step)
  config = tiny_config("gridworld.py", *_overrides(data_dir, **{
      "train.checkpoint_every": 1, "train.num_steps": 10, "batch_size": 8}))
  with pytest.raises(NonFiniteLossError, match=r"loss is nan at step 4.*last good checkpoint "
                     r"\(step 3\)"):
    train(config, str(tmp_path))
  assert ocp.CheckpointManager(str(tmp_path / "checkpoints")).latest_step() == 3
  for value in _flatten(_state(tmp_path, 3)["params"]).values():
    assert np.isfinite(value).all()


@pytest.mark.parametrize("override,message", [
    ("data.dataset='rt2'", "unknown dataset 'rt2'"),
    ("model.action_dim=7", "gridworld has 4-dim actions but the model expects model.action_dim=7"),
    ("batch_size=6", "global batch_size 6 is not divisible by the data-parallel size 8"),
    ("frame_shape=(64, 64, 3)", r"frame_shape \(64, 64, 3\) does not match"),
])
def test_bad_setups_fail_before_compilation(data_dir, tmp_path, override, message):
  config = tiny_config("gridworld.py", *_overrides(data_dir, batch_size=8), override)
  with pytest.raises(ValueError, match=message):
    train(config, str(tmp_path))
