"""A run is never lost or silently changed (issue 20): finite checkpoints only, config checks on
resume, damaged checkpoints, failed saves, the workdir lock, signals and exit codes, and inputs
refused at the command line. The suite's tiny trained workdir is shared (conftest.py); a test that
resumes or damages it takes a copy."""

import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from conftest import (GRIDWORLD_DATA, gridworld_config, gridworld_overrides, one_line_error,
                      tiny_config)
from wmjax import cli, parallel
from wmjax.config import ConfigError, load_config
from wmjax.data.pipeline import WindowSource, training_pipeline
from wmjax.data.sources import ArrayRecordEpisodes, action_stats
from wmjax.errors import CheckpointError
from wmjax.eval import inputs
from wmjax.model import WorldModel, load_model
from wmjax.tasks.gridworld import dataset as gridworld
from wmjax.train.checkpoint import Checkpointer
from wmjax.train.loop import NonFiniteLossError, initial_weights, train
from wmjax.train.resume import ConfigChangeError, check_resume
from wmjax.train.step import ShardedTrainer
from wmjax.train.workdir import LOCK_NAME, WorkdirLock, WorkdirLockedError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cli_train(workdir, data_dir, *flags, **extra):
  """``wmjax train`` in this process; returns its exit code."""
  overrides = [f"--config.{v}" for v in gridworld_overrides(data_dir, **extra)]
  return cli.main(["train", "--config", os.path.join(ROOT, "configs", "gridworld.py"),
                   "--workdir", str(workdir)] + overrides + list(flags))


def _steps(workdir):
  return sorted(int(p) for p in os.listdir(os.path.join(workdir, "checkpoints")) if p.isdigit())


def _logged(workdir):
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    return [json.loads(line) for line in f]


def _patched_step(nan_from=None, then=None):
  """A train step whose parameters become NaN from step ``nan_from`` on (as a diverged run's);
  ``then(step)`` runs after every step."""
  real_step = ShardedTrainer.step

  def step(self, state, frames, actions):
    state, metrics = real_step(self, state, frames, actions)
    if nan_from is not None and int(state.step) >= nan_from:
      state = state.replace(params=jax.tree.map(lambda p: p * jnp.nan, state.params))
    if then is not None:
      then(int(state.step))
    return state, metrics

  return step


# ----------------------------------------------------------------------------- 1, 8, 10


@pytest.mark.integration
@pytest.mark.slow
def test_sigterm_never_saves_a_nan_state(data_dir, tmp_path, monkeypatch):
  """1: SIGTERM after the state went NaN (no loss was checked: log_every is large) saves
  nothing, and the message does not claim a checkpoint that does not exist (8)."""
  def terminate(step):
    if step == 3:
      os.kill(os.getpid(), signal.SIGTERM)

  monkeypatch.setattr(ShardedTrainer, "step", _patched_step(nan_from=3, then=terminate))
  config = gridworld_config(data_dir, **{"train.num_steps": 50, "train.log_every": 1000,
                                "train.checkpoint_every": 1000})
  with pytest.raises(NonFiniteLossError, match=r"state at step 3 holds NaN or inf values and was "
                     r"not saved.*No checkpoint was saved yet") as error:
    train(config, str(tmp_path))
  assert "last good checkpoint" not in str(error.value)
  assert _steps(tmp_path) == []


@pytest.mark.integration
@pytest.mark.slow
def test_nan_on_a_fresh_run_names_no_checkpoint_and_advises_tighter_clipping(data_dir, tmp_path,
                                                                             monkeypatch):
  """8: the loss goes NaN before any checkpoint: the advice is a smaller grad_clip."""
  real_step = ShardedTrainer.step

  def step(self, state, frames, actions):
    state, metrics = real_step(self, state, frames, actions)
    return state, dict(metrics, loss=metrics["loss"] * jnp.nan)

  monkeypatch.setattr(ShardedTrainer, "step", step)
  with pytest.raises(NonFiniteLossError) as error:
    train(gridworld_config(data_dir), str(tmp_path))
  message = str(error.value)
  assert "loss is nan at step 1" in message and "No checkpoint was saved yet" in message
  assert "a smaller optim.grad_clip" in message and "raise optim.grad_clip" not in message
  assert "step 0" not in message


@pytest.mark.integration
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
@pytest.mark.slow
def test_a_signal_saves_and_exits_128_plus_its_number(data_dir, tmp_path, monkeypatch, capsys,
                                                     signum):
  """10: Ctrl-C (SIGINT) and a scheduler's SIGTERM save the current step and make `wmjax train`
  exit 128 + the signal number (130 / 143: unfinished); the handler before the run is back."""
  def interrupt(step):
    if step == 3:
      os.kill(os.getpid(), signum)

  monkeypatch.setattr(ShardedTrainer, "step", _patched_step(then=interrupt))
  handler = signal.getsignal(signum)
  assert _cli_train(tmp_path, data_dir, **{"train.num_steps": 50}) == 128 + signum
  assert _steps(tmp_path) == [2, 3]
  out = capsys.readouterr().out
  assert f"{signum.name}: saved step 3" in out and json.loads(out[out.index("{"):])["step"] == 3
  assert signal.getsignal(signum) is handler


# ----------------------------------------------------------------------------- 2, 3, 12


@pytest.mark.integration
@pytest.mark.slow
def test_resume_refuses_a_changed_config_and_keeps_config_json(trained_copy, data_dir):
  """2: a changed objective is refused with the differing key; config.json is untouched."""
  before = (trained_copy / "config.json").read_text()
  with pytest.raises(ConfigChangeError, match=r"(?s)diffusion.prediction: 'x0' \(checkpoint\) -> "
                     r"'eps' \(now\).*--allow_config_change=diffusion.prediction"):
    train(gridworld_config(data_dir, **{"diffusion.prediction": "eps"}), str(trained_copy))
  assert (trained_copy / "config.json").read_text() == before
  assert _steps(trained_copy) == [2, 4]


@pytest.mark.integration
@pytest.mark.slow
def test_config_changes_safe_on_resume_or_named_are_accepted_and_recorded(trained_copy, data_dir):
  """2: train.num_steps is always accepted, a named change is accepted, both are recorded."""
  config = gridworld_config(data_dir, **{"optim.learning_rate": 1e-3, "train.num_steps": 5})
  train(config, str(trained_copy), allow_config_change=["optim"])
  record = json.loads((trained_copy / "config_changes.jsonl").read_text())
  assert record["step"] == 4 and record["changes"]["train.num_steps"]["accepted"] == "safe"
  assert record["changes"]["optim.learning_rate"] == {"checkpoint": 3e-3, "now": 1e-3,
                                                      "accepted": "optim"}
  assert json.loads((trained_copy / "config.json").read_text())["optim"]["learning_rate"] == 1e-3
  assert _steps(trained_copy) == [2, 4, 5]


@pytest.mark.integration
@pytest.mark.slow
def test_layers_trained_scanned_resume_and_load_unrolled(trained_copy, data_dir):
  """model.scan_layers may change on resume (accepted as safe, parameters and optimiser state
  unstacked) and on loading: either layout reads into either, and computes the same."""
  train(gridworld_config(data_dir, **{"model.scan_layers": False, "train.num_steps": 5}),
        str(trained_copy))
  record = json.loads((trained_copy / "config_changes.jsonl").read_text())
  assert record["changes"]["model.scan_layers"] == {"checkpoint": True, "now": False,
                                                    "accepted": "safe"}
  stored = Checkpointer(str(trained_copy / "checkpoints")).stored_shapes(5)
  assert not any("/layers/" in k for k in stored)
  assert any(k.startswith("opt_state/") and "/blocks/layer_0/" in k for k in stored)
  scanned = load_model(str(trained_copy), step=4)
  unrolled = load_model(str(trained_copy), step=4, overrides=["model.scan_layers=False"])
  assert "layer_0" in unrolled.params["params"]["blocks"]
  key = jax.random.key(0)
  x = jax.random.normal(key, (2, 6, 16, 16, 3))
  levels, actions = jnp.full((2, 6), 500), jax.random.normal(key, (2, 5, 4))
  mask = jnp.ones((2, 5), bool)
  np.testing.assert_allclose(unrolled.world_model.denoise(unrolled.params, x, levels, actions, mask),
                             scanned.world_model.denoise(scanned.params, x, levels, actions, mask),
                             rtol=1e-5, atol=1e-5)
  later = load_model(str(trained_copy), step=5, overrides=["model.scan_layers=True"])
  assert set(later.params["params"]["blocks"]) == {"layers"}


@pytest.mark.integration
@pytest.mark.slow
def test_init_from_starts_a_new_run_from_another_runs_weights(trained_workdir, data_dir, tmp_path):
  """train.init_from: a new run (unrolled layers here) starts from the EMA weights of another
  workdir's newest checkpoint; a model of other shapes, or of the same shapes computing another
  function (other positions), is one clear error."""
  source = str(trained_workdir)
  # learning rate 0: the one step leaves the weights as they came (the EMA of equal weights too)
  train(gridworld_config(data_dir, **{"train.init_from": repr(source), "model.scan_layers": False,
                                      "optim.learning_rate": 0.0, "train.num_steps": 1,
                                      "train.checkpoint_every": 1}), str(tmp_path / "tuned"))
  tuned = load_model(str(tmp_path / "tuned"), params="raw", overrides=["model.scan_layers=True"])
  assert jax.tree.all(jax.tree.map(lambda a, b: bool((a == b).all()), tuned.params,
                                   load_model(source).params))
  for key, value, message in (("model.hidden_size", 64, r"model.hidden_size \(32 there, 64 here\)"),
                              ("model.spatial_pos", "'sincos'",
                               r"model.spatial_pos \('rope' there, 'sincos' here\)")):
    with pytest.raises(ConfigChangeError, match=r"train.init_from=.*its model differs from this "
                       r"config's in " + message + r"; set them as it has them"):
      initial_weights(gridworld_config(data_dir, **{"train.init_from": repr(source), key: value}))


@pytest.mark.integration
@pytest.mark.slow
def test_shape_change_on_resume_is_one_clear_error(trained_copy, data_dir, capfd):
  """3: a wider model stops at once with one message naming the key, no traceback."""
  assert _cli_train(trained_copy, data_dir, **{"model.hidden_size": 64}) == 1
  err = capfd.readouterr().err
  message = err[err.index("wmjax train:"):]
  assert "model.hidden_size: 32 (checkpoint) -> 64 (now)" in message
  assert "Traceback" not in err and "Event loop is closed" not in err
  assert len(message.strip().splitlines()) <= 4


@pytest.mark.integration
def test_unknown_config_keys_and_unshardable_meshes_fail_early(data_dir, tmp_path, capsys):
  """12: a misspelt key names the right one; a mesh that cannot split the heads is refused
  before compilation; --help documents overrides and resuming."""
  with pytest.raises(ConfigError, match=r"unknown config key 'model.depht'; did you mean "
                     r"model.depth\?"):
    load_config(os.path.join(ROOT, "configs", "gridworld.py"), ["model.depht=3"])
  assert _cli_train(tmp_path, data_dir, "--config.model.depht=3") == 2
  assert "did you mean model.depth?" in capsys.readouterr().err
  config = gridworld_config(data_dir, mesh=(2, 1, 4))  # 2 heads over a 4-way tensor axis
  with pytest.raises(ValueError, match=r"'heads' axis \(model.num_heads\).*tensor axis \(4\)"):
    train(config, str(tmp_path))
  wm = WorldModel.from_config(tiny_config("gridworld.py", "model.num_heads=4"))
  abstract = jax.eval_shape(lambda: wm.init(jax.random.key(0), (16, 16, 3), 6))
  with pytest.raises(ValueError, match="does not divide"):
    parallel.check_shardable(abstract, parallel.make_mesh((2, 1, 3), jax.devices()[:6]))
  for command in ("train", "evaluate", "rollout"):
    with pytest.raises(SystemExit):
      cli.main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--config.KEY=VALUE" in text, command
  with pytest.raises(SystemExit):
    cli.main(["train", "--help"])
  text = " ".join(capsys.readouterr().out.split())
  assert "train.num_steps, train.log_every, train.eval_every" in text and "143 / 130" in text


# ----------------------------------------------------------------------------- 4


@pytest.mark.integration
@pytest.mark.slow
def test_a_failed_background_save_stops_training_at_once(data_dir, tmp_path, monkeypatch):
  """4: the disk fills up while checkpoint 4 is written in the background: training stops
  before the next checkpoint is due, with a one-line message; checkpoint 2 stays, the partial
  write is removed."""
  real_save = ocp.JsonCheckpointHandler._save_fn

  async def full_disk(self, x, directory):
    if "4.orbax-checkpoint-tmp" in str(directory):
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return await real_save(self, x, directory)

  monkeypatch.setattr(ocp.JsonCheckpointHandler, "_save_fn", full_disk)
  real_step = ShardedTrainer.step

  def slow_step(self, state, frames, actions):  # leave the failing save time to finish
    if int(state.step) >= 4:
      import time
      time.sleep(1.0)
    return real_step(self, state, frames, actions)

  monkeypatch.setattr(ShardedTrainer, "step", slow_step)
  config = gridworld_config(data_dir, **{"train.num_steps": 16})
  with pytest.raises(CheckpointError, match=r"saving checkpoint 4 .* failed: the disk is full "
                     r"\(No space left on device.*checkpoint 2 is intact") as error:
    train(config, str(tmp_path))
  assert "\n" not in str(error.value)
  assert max(row["step"] for row in _logged(tmp_path)) < 6  # before the next save
  assert _steps(tmp_path) == [2]
  assert not [p for p in os.listdir(tmp_path / "checkpoints") if "tmp" in p]


@pytest.mark.integration
def test_checkpointer_poll_raises_once_the_failed_save_has_finished(tmp_path, monkeypatch):
  real_save = ocp.JsonCheckpointHandler._save_fn

  async def failing(self, x, directory):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  checkpoints = Checkpointer(str(tmp_path / "ckpt"))
  checkpoints.save(1, {"w": jnp.ones(3)}, {"a": 1}, {"b": 2})
  checkpoints.wait()
  monkeypatch.setattr(ocp.JsonCheckpointHandler, "_save_fn", failing)
  checkpoints.save(2, {"w": jnp.ones(3)}, {"a": 1}, {"b": 2})
  while checkpoints.manager.is_saving_in_progress():
    pass
  with pytest.raises(CheckpointError, match="checkpoint 1 is intact"):
    checkpoints.poll()
  monkeypatch.setattr(ocp.JsonCheckpointHandler, "_save_fn", real_save)
  checkpoints.close()
  assert checkpoints.all_steps() == [1]


# ----------------------------------------------------------------------------- 5


@pytest.mark.integration
@pytest.mark.slow
def test_damaged_latest_checkpoint_falls_back_with_a_warning(trained_copy, data_dir, capfd):
  """5: a truncated array file of checkpoint 4: the run resumes from 2, says so naming both,
  and keeps the damaged checkpoint aside; reading it for inference names the file and --step."""
  data = sorted((trained_copy / "checkpoints" / "4" / "state" / "d").iterdir())[0]
  data.write_bytes(data.read_bytes()[:50])
  with pytest.raises(CheckpointError, match=r"checkpoint 4 cannot be read: .*checkpoints/4/state"
                     r".*pass --step 2"):
    load_model(str(trained_copy))
  train(gridworld_config(data_dir), str(trained_copy))
  err = capfd.readouterr().err
  assert "checkpoint 4 cannot be read" in err and "resuming from checkpoint 2" in err
  assert "Event loop is closed" not in err
  assert _steps(trained_copy) == [2, 4] and (trained_copy / "damaged_checkpoints" / "4" / "state").is_dir()
  assert load_model(str(trained_copy)).step == 4
  (trained_copy / "checkpoints" / "2" / "config" / "metadata").write_text("")  # unreadable config
  with pytest.raises(CheckpointError, match=r"checkpoints/2/config: JSONDecodeError.*--step 4"):
    load_model(str(trained_copy), step=2)


# ----------------------------------------------------------------------------- 6, 7, 9


@pytest.mark.integration
@pytest.mark.slow
def test_batches_do_not_depend_on_the_number_of_workers(data_dir):
  """6: batch k is the same with 0 or 2 worker processes, and ``start`` skips to it."""
  builder_dir = gridworld.prepare(str(data_dir), GRIDWORLD_DATA)
  source = WindowSource(ArrayRecordEpisodes(builder_dir, "train"), 6, 1, None)
  stats = [action_stats(builder_dir)]

  def batches(workers, start=0, n=5):
    it = iter(training_pipeline([source], stats, batch_size=4, seed=2, shard_index=0,
                                shard_count=1, num_workers=workers, start=start))
    out = [next(it) for _ in range(n)]
    it.close()
    return out

  # start with worker processes: test_resume_with_more_workers_logs_each_step_once_and_cleans_up
  sequential, parallel_workers, later = batches(0), batches(2), batches(0, start=3, n=2)
  for a, b in zip(sequential, parallel_workers):
    np.testing.assert_array_equal(a["frames"], b["frames"])
  for a, b in zip(sequential[3:], later):
    np.testing.assert_array_equal(a["episode"], b["episode"])
    np.testing.assert_array_equal(a["start"], b["start"])


@pytest.mark.integration
@pytest.mark.slow
def test_resume_with_more_workers_logs_each_step_once_and_cleans_up(trained_copy, data_dir):
  """6, 7, 9: the run died after logging step 4 but before checkpoint 4 completed, leaving a
  temporary checkpoint and a stale lock; it resumes from 2 with 2 data workers, reads the same
  batches, logs steps 3 and 4 once, and removes the temporary directory."""
  first = {row["step"]: row["batch"] for row in _logged(trained_copy)}
  shutil.move(trained_copy / "checkpoints" / "4", trained_copy / "checkpoints" / "4.orbax-checkpoint-tmp")
  dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                        capture_output=True, text=True).stdout.strip()
  (trained_copy / LOCK_NAME).write_text(json.dumps({"pid": int(dead), "host": socket.gethostname()}))
  train(gridworld_config(data_dir, **{"data.num_workers": 2}), str(trained_copy))
  rows = _logged(trained_copy)
  assert [row["step"] for row in rows] == [1, 2, 3, 4]
  assert {row["step"]: row["batch"] for row in rows} == first
  assert sorted(os.listdir(trained_copy / "checkpoints")) == ["2", "4"]
  assert not (trained_copy / LOCK_NAME).exists()


@pytest.mark.integration
def test_a_second_trainer_in_the_workdir_is_refused(data_dir, tmp_path):
  """7: while one process holds the workdir, another train stops at once naming it."""
  holder = WorkdirLock(str(tmp_path))
  holder.acquire()
  try:
    with pytest.raises(WorkdirLockedError, match=rf"in use by another `wmjax train` \(pid "
                       rf"{os.getpid()} on {socket.gethostname()}"):
      train(gridworld_config(data_dir), str(tmp_path))
  finally:
    holder.release()
  assert not (tmp_path / "checkpoints").exists()


@pytest.mark.integration
def test_an_early_failure_removes_the_workdir_it_made_and_keeps_one_that_was_there(data_dir,
                                                                                    tmp_path):
  """Issue 49: a run that stops before writing anything (here a mesh the heads do not fit)
  leaves no empty workdir, nor the parents it made; a workdir that existed stays, with what it
  held."""
  config = gridworld_config(data_dir, mesh=(2, 1, 4))
  with pytest.raises(ValueError, match="does not divide"):
    train(config, str(tmp_path / "runs" / "new"))
  assert os.listdir(tmp_path) == []
  for kept in ({}, {"notes.txt": "mine"}):
    workdir = tmp_path / f"existing{len(kept)}"
    workdir.mkdir()
    for name, text in kept.items():
      (workdir / name).write_text(text)
    with pytest.raises(ValueError, match="does not divide"):
      train(config, str(workdir))
    assert sorted(os.listdir(workdir)) == sorted(kept)


# ----------------------------------------------------------------------------- 11


@pytest.mark.integration
@pytest.mark.slow
def test_commands_refuse_unknown_flags_and_out_of_range_inputs(trained_workdir, tmp_path, capsys):
  """11: unknown flags, --horizon 0, ambiguous float frames and absurd actions are errors."""
  with pytest.raises(SystemExit) as exit_:
    cli.main(["data", "stats", str(tmp_path), "--splt", "test"])
  assert exit_.value.code == 2 and "unrecognized arguments: --splt" in capsys.readouterr().err
  frames = np.zeros((1, 16, 16, 3), np.float32)
  frames[0, 4:8, 4:8] = 1.0  # a white square on black, as a [0, 1] image
  np.save(tmp_path / "frames.npy", frames)
  np.save(tmp_path / "actions.npy", np.zeros((5, 4), np.float32))
  base = ["rollout", "--workdir", str(trained_workdir), "--actions", str(tmp_path / "actions.npy"),
          "--out", str(tmp_path / "out")]
  one_line_error(capsys, base + ["--frames", str(tmp_path / "frames.npy")],
                 r"ambiguous.*--frame_range 0,1")
  as_uint8 = inputs.read_frames([str(tmp_path / "frames.npy")], (16, 16, 3), value_range="0,1")
  assert as_uint8.max() == 255 and as_uint8.min() == 0
  with pytest.raises(SystemExit, match=r"--horizon must be between 1 and 5.*got 0"):
    cli.main(base + ["--frames", str(tmp_path / "frames.npy"), "--frame_range", "0,1",
                     "--horizon", "0"])
  np.save(tmp_path / "huge.npy", np.full((5, 4), 1e30, np.float32))
  one_line_error(capsys, base[:3] + ["--actions", str(tmp_path / "huge.npy"), "--out",
                                     str(tmp_path / "o"), "--frames", str(tmp_path / "frames.npy"),
                                     "--frame_range", "0,1"],
                 r"action dimension 0 takes values in \[1e\+30, 1e\+30\], but the model was "
                 r"trained on")
  assert not (tmp_path / "out").exists() and not (tmp_path / "o").exists()


@pytest.mark.unit
def test_check_resume_accepts_only_safe_or_named_changes():
  saved = {"train": {"num_steps": 10}, "optim": {"learning_rate": 1e-3}, "mesh": [-1, 1, 1]}
  now = {"train": {"num_steps": 20}, "optim": {"learning_rate": 1e-4}, "mesh": [1, 8, 1]}
  with pytest.raises(ConfigChangeError, match=r"optim.learning_rate: 0.001 \(checkpoint\)"):
    check_resume(3, saved, now, {}, {})
  changes, by = check_resume(3, saved, now, {}, {}, allow=["optim.learning_rate"])
  assert by == {"train.num_steps": "safe", "mesh": "safe",
                "optim.learning_rate": "optim.learning_rate"}
  with pytest.raises(ConfigChangeError, match="cannot change the shapes of its parameters"):
    check_resume(3, saved, saved, {"w": (2, 3)}, {"w": (2, 4)}, allow=["model"])


@pytest.mark.integration
def test_bad_inputs_end_in_one_line_with_exit_2(tmp_path, capsys, monkeypatch):
  """What a newcomer's own data and flags can get wrong: one line on stderr, exit 2; the
  traceback with WMJAX_DEBUG=1."""
  missing = str(tmp_path / "nowhere")
  grid = os.path.join(ROOT, "configs", "gridworld.py")
  one_line_error(capsys, ["data", "inspect", missing], "nowhere")
  one_line_error(capsys, ["train", "--config", os.path.join(ROOT, "configs", "rlds.py"),
                          "--workdir", str(tmp_path / "w"), f"--config.data.builder_dir={missing}"],
                 "no TFDS dataset at")
  one_line_error(capsys, ["train", "--config", grid, "--workdir", str(tmp_path / "w2"),
                          "--config.data.frames=6"], "exceeds model.num_frames")
  one_line_error(capsys, ["data", "import", "lerobot", missing, str(tmp_path / "out")],
                 "is not a LeRobot dataset: no meta/info.json")
  one_line_error(capsys, ["data", "encode", "--config", os.path.join(ROOT, "configs", "bridge.py"),
                          "--out", str(tmp_path / "enc"), f"--config.codec.path={missing!r}"],
                 "AutoencoderKL folder .*, which is not there; without the VAE, "
                 "--config.codec.kind=pixel")
  monkeypatch.setenv("WMJAX_DEBUG", "1")
  with pytest.raises(ValueError, match="exceeds model.num_frames"):
    cli.main(["train", "--config", grid, "--workdir", str(tmp_path / "w3"),
              "--config.data.frames=6"])


_TPU_PROBE = """
import sys
from jax._src import xla_bridge
started = []
real = xla_bridge.make_tpu_client
xla_bridge.make_tpu_client = lambda *a, **k: started.append(1) or real(*a, **k)
if sys.argv[1] == "wmjax":
  import wmjax  # noqa: F401
import jax
jax.devices()
print("started" if started else "not started")
"""


@pytest.mark.integration
@pytest.mark.slow
def test_a_machine_without_tpu_chips_starts_no_tpu_client():
  """libtpu (the test extra) makes JAX start a TPU client everywhere, and libtpu then prints
  INVALID_ARGUMENT lines on a CPU host; importing wmjax leaves the TPU out when the machine has
  none (every wmjax command, experiment script and notebook imports it first)."""
  pytest.importorskip("libtpu")
  from jax._src import hardware_utils
  if hardware_utils.num_available_tpu_chips_and_device_id()[0]:
    pytest.skip("this machine has TPU chips")
  env = {k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "JAX_FORCE_TPU_INIT")}
  probe = [sys.executable, "-c", _TPU_PROBE]
  run = lambda mode: subprocess.run(probe + [mode], env=env, capture_output=True, text=True,  # noqa: E731
                                    check=True)
  assert run("plain").stdout.strip() == "started"  # what importing wmjax prevents
  skipped = run("wmjax")
  assert skipped.stdout.strip() == "not started"
  assert "INVALID_ARGUMENT" not in skipped.stderr and "libtpu" not in skipped.stderr
