"""Shared test helpers: tiny configs of the shipped config files and perturbed parameters.

Tests run on 8 simulated CPU devices so that sharding is exercised.
"""

import fcntl
import functools
import importlib.util
import os
import shutil
import tempfile

# 8 simulated devices for the sharding tests. The tiny test programs spend far longer in XLA's
# CPU compiler than they run, so its LLVM backend skips its optimisations (the whole suite 1383 s
# -> 843 s on two workers) and it emits fused loops with its older elemental emitters, which
# compile a third faster (tiny STDiT init + grad compiles 8.3 s -> 5.0-5.7 s; the suite 835 s
# without them in one session, 706 s with them in the next). A test that runs a step many times
# compiles that step with the default level (test_overfit.py).
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=8"
                           + " --xla_backend_optimization_level=0"
                           + " --xla_cpu_use_fusion_emitters=false").strip()

# One persistent compilation cache for the run, shared through the environment with the
# processes it starts (`wmjax train` subprocesses, notebook kernels, pytest-xdist workers): the
# suite compiles the same tiny models again and again, in module after module (the fixture below
# drops the in-memory programs) and in every subprocess. A fresh directory per run, removed at
# the end by the process that made it, so that every run still compiles everything once.
_CACHE_VARIABLE = "WMJAX_TEST_COMPILATION_CACHE"
_OWN_CACHE = _CACHE_VARIABLE not in os.environ
if _OWN_CACHE:
  os.environ[_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="wmjax-test-xla-cache-")
os.environ.update(JAX_COMPILATION_CACHE_DIR=os.environ[_CACHE_VARIABLE],
                  JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                  JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")

from pathlib import Path  # noqa: E402  (the variables above must be set before jax is imported)

import flax.linen as nn  # noqa: E402
import jax  # noqa: E402
import pytest  # noqa: E402
from jax import flatten_util  # noqa: E402

from wmjax.config import load_config  # noqa: E402
from wmjax.model import WorldModel  # noqa: E402
from wmjax.tasks.gridworld import dataset as gridworld  # noqa: E402
from wmjax.train.loop import train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

TINY = ("model.depth=2", "model.hidden_size=32", "model.num_heads=2", "model.num_frames=8",
        "data.frames=8")


def tiny_config(config: str = "irasim.py:S", *overrides: str):
  """A shipped config shrunk to a tiny width, updated by ``key=value`` overrides."""
  return load_config(str(ROOT / "configs" / config), TINY + overrides)


# the sharded-training tests' tiny gridworld model (8x8x3 frames, 4-dim actions) and its batches
TRAIN_OVERRIDES = ("model.in_channels=3", "model.action_dim=4", "model.hidden_size=32",
                   "model.num_heads=4", "optim.grad_clip=0.1")


def train_batch(seed=0, batch=8, frames=4):
  """Random (frames ``[batch, frames, 8, 8, 3]`` in [-1, 1], actions ``[batch, frames - 1, 4]``)."""
  k1, k2 = jax.random.split(jax.random.key(seed))
  return (jax.random.uniform(k1, (batch, frames, 8, 8, 3), minval=-1, maxval=1),
          jax.random.normal(k2, (batch, frames - 1, 4)))


@functools.partial(jax.jit, static_argnames="scale")
def perturbed(params, key, scale: float = 0.1):
  """Add noise to every parameter: adaLN-Zero makes a fresh model ignore its conditioning."""
  flat, unravel = flatten_util.ravel_pytree(params)
  return unravel(flat + scale * jax.random.normal(key, flat.shape, flat.dtype))


def jit_apply(module: nn.Module):
  """``module.apply``, compiled once per input shape. Called eagerly, a Flax module runs every
  operation as its own XLA program, and compiling those hundreds of programs is most of a test's
  time on a CPU."""
  return jax.jit(module.apply, static_argnames=("method", "train", "mutable"))


def tiny_world_model(config: str = "irasim.py:S", *overrides: str, frame_shape=(8, 8, 4), seed=0):
  """(WorldModel, perturbed params) of a tiny config."""
  wm = WorldModel.from_config(tiny_config(config, *overrides))
  params = wm.init(jax.random.key(seed), frame_shape)
  return wm, perturbed(params, jax.random.key(seed + 1))


TIERS = ("unit", "integration")

# The README's test command gives each pytest-xdist worker whole modules (--dist loadfile), by
# default the modules with the most tests first, which leaves the few long modules (the overfit
# test, the notebooks) to the end, on one worker while the other idles. The longest modules go
# first instead, longest first (the 2026-11-29 durations in benchmarks/RESULTS.md), the others
# after them in file order.
LONGEST_MODULES = ("test_pusht.py", "test_dit.py", "test_run_integrity.py", "test_recipes.py",
                   "test_train_loop.py", "test_fit.py", "test_rollout.py", "test_documentation.py",
                   "test_train.py", "test_evaluate.py", "test_notebooks.py", "test_data_specs.py",
                   "test_vae.py", "test_overfit.py")


def pytest_configure(config):
  if hasattr(config.option, "loadscopereorder"):  # pytest-xdist's reordering by test count
    config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
  """Every test sits in exactly one tier (pyproject.toml registers the markers); the longest
  modules run first."""
  first = {name: rank for rank, name in enumerate(LONGEST_MODULES)}
  items.sort(key=lambda item: first.get(item.path.name, len(first)))  # stable: file order after
  untiered = [item.nodeid for item in items
              if sum(item.get_closest_marker(tier) is not None for tier in TIERS) != 1]
  if untiered:
    raise pytest.UsageError(
        f"{len(untiered)} tests carry not exactly one of the markers {TIERS} (mark a module with "
        "`pytestmark = pytest.mark.unit`, or a test with a decorator): " + ", ".join(untiered[:10]))


def pytest_unconfigure(config):
  if _OWN_CACHE:
    shutil.rmtree(os.environ.pop(_CACHE_VARIABLE), ignore_errors=True)


@pytest.fixture
def rng():
  return jax.random.key(0)


# PyTorch and diffusers (the test extra) are imported by the tests that compare against them, not
# at collection, where every pytest-xdist worker would pay 4-5 s for them.
@pytest.fixture(scope="session")
def torch():
  return pytest.importorskip("torch")


@pytest.fixture(scope="session")
def diffusers(torch):
  return pytest.importorskip("diffusers")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
  """Drop every module's compiled programs when it ends: the suite compiles hundreds of them
  (interpret-mode Pallas attention among them), and one process keeps them all otherwise."""
  yield
  jax.clear_caches()


def built_once(tmp_path_factory, name: str, build) -> Path:
  """The directory ``name`` that ``build(path)`` fills once per test run, shared by every test
  and by both pytest-xdist workers: the first to ask builds it under a file lock in the run's
  temporary directory, the others wait and reuse it. Read-only for the tests."""
  base = tmp_path_factory.getbasetemp()
  if os.environ.get("PYTEST_XDIST_WORKER"):
    base = base.parent  # the run's directory, above each worker's own
  path, built = base / name, base / f"{name}.built"
  with open(base / f"{name}.lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
    if not built.exists():
      shutil.rmtree(path, ignore_errors=True)  # what a failed build left
      build(path)
      built.touch()
  return path


GRIDWORLD_DATA = gridworld.GridworldConfig(train_episodes=16, test_episodes=2, episode_length=12)


@pytest.fixture(scope="session")
def data_dir(tmp_path_factory):
  """A small gridworld (16 train, 2 test episodes of 12 steps) for training-loop tests; built
  once per run, read-only for the tests."""
  return built_once(tmp_path_factory, "gridworld-data",
                    lambda path: gridworld.prepare(str(path), GRIDWORLD_DATA))


def pusht_experiment_script(name: str = "run"):
  """``experiments/pusht/NAME.py`` as a module."""
  spec = importlib.util.spec_from_file_location(f"pusht_{name}",
                                                ROOT / f"experiments/pusht/{name}.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


# experiments/pusht/run.py --smoke shrunk further: 16x16 frames, 6 + 2 short episodes, 2 steps
PUSHT_EXPERIMENT_TINY = [
    "--smoke", "--video_format", "gif", "--success_coverage", "0.1",
    "--config.data.pusht.image_size=16", "--config.frame_shape=(16,16,3)",
    "--config.data.pusht.episode_length=10", "--config.data.pusht.train_episodes=6",
    "--config.data.pusht.test_episodes=2", "--config.data.pusht.batch=6",
    "--config.train.num_steps=2", "--config.optim.total_steps=2", "--config.optim.warmup_steps=1",
    "--config.train.checkpoint_every=2", "--config.train.eval_every=0",
    "--config.sampling.num_steps=2"]


@pytest.fixture(scope="session")
def pusht_experiment(tmp_path_factory) -> Path:
  """The workdir of ``experiments/pusht/run.py``'s first stages at ``PUSHT_EXPERIMENT_TINY``: its
  data, success classifier and a tiny world model (``model/``), once per test run for the tests
  that need a trained Push-T model. Read-only: a test copies what it writes into."""
  stages = ["--stage", "data", "--stage", "classifier", "--stage", "train"]

  def build(path):
    args = ["--workdir", str(path)] + PUSHT_EXPERIMENT_TINY + stages
    assert pusht_experiment_script().main(args) == 0

  return built_once(tmp_path_factory, "pusht-experiment", build)


def gridworld_overrides(data_dir, **extra) -> list[str]:
  """``key=value`` overrides of configs/gridworld.py for a tiny run on ``data_dir`` (the
  ``data_dir`` fixture's ``GRIDWORLD_DATA``): 6-frame windows rolled out 1 + 5, 4 steps of batch
  8, checkpoints 2 and 4, every step logged, no evaluation in the loop; ``extra`` changes or adds
  keys."""
  values = {
      "data.data_dir": repr(str(data_dir)),
      "data.gridworld.train_episodes": GRIDWORLD_DATA.train_episodes,
      "data.gridworld.test_episodes": GRIDWORLD_DATA.test_episodes,
      "data.gridworld.episode_length": GRIDWORLD_DATA.episode_length,
      "model.depth": 2, "model.hidden_size": 32, "model.num_heads": 2, "model.patch_size": 4,
      "model.num_frames": 6, "data.frames": 6, "rollout.horizon": 5,
      "rollout.short_actions": None, "batch_size": 8, "train.num_steps": 4,
      "train.log_every": 1, "train.checkpoint_every": 2, "train.eval_every": 0,
      "train.eval_windows": 2, "sampling.num_steps": 2, "optim.warmup_steps": 1,
      "optim.total_steps": 4}
  values.update(extra)
  return [f"{k}={v}" for k, v in values.items()]


def gridworld_config(data_dir, **extra):
  return load_config(str(ROOT / "configs" / "gridworld.py"), gridworld_overrides(data_dir, **extra))


@pytest.fixture(scope="session")
def trained_workdir(data_dir, tmp_path_factory):
  """The workdir of ``gridworld_config(data_dir)`` trained (checkpoints 2 and 4): once per test
  run for every test that needs *a* trained model. Read-only: a test that writes into a workdir
  takes ``trained_copy``."""
  path = built_once(tmp_path_factory, "gridworld-trained",
                    lambda path: train(gridworld_config(data_dir), str(path)))
  before = _files(path)
  yield path
  assert _files(path) == before, "a test wrote into trained_workdir (take trained_copy)"


def _files(root: Path) -> dict[str, tuple[int, int]]:
  """Every file under ``root``: its size and modification time."""
  return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
          for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def trained_copy(trained_workdir, tmp_path):
  """A copy of ``trained_workdir`` of the test's own, to resume, damage or write into."""
  return shutil.copytree(trained_workdir, tmp_path / "run")


# the widths and steps the own-data tests add to the training command `wmjax data inspect` prints
OWN_DATA_TINY = {"data.resolution": (16, 16), "frame_shape": (16, 16, 3), "model.depth": 2,
                 "model.hidden_size": 32, "model.num_heads": 2, "batch_size": 8,
                 "train.num_steps": 1, "train.eval_every": 0}


def inspected_command(capsys, builder_dir: str, workdir: str) -> tuple[str, list[str]]:
  """``wmjax data inspect BUILDER_DIR``: what it printed, and the ``wmjax train`` command it ends
  with for ``workdir`` (its config file named by its full path: it runs from any directory)."""
  import shlex

  from wmjax import cli
  capsys.readouterr()
  assert cli.main(["data", "inspect", builder_dir]) == 0
  printed = capsys.readouterr().out
  command = shlex.split(printed.splitlines()[-1].replace("WORKDIR", workdir))
  assert command[:2] == ["wmjax", "train"]
  at = command.index("--config") + 1
  assert command[at] == str(ROOT / "configs" / "rlds.py")
  return printed, command


def one_line_error(capsys, argv: list[str], pattern: str) -> str:
  """Run ``wmjax argv``: it must exit 2 with one line on stderr matching ``pattern``."""
  import re

  from wmjax import cli
  capsys.readouterr()
  code = cli.main(argv)
  err = capsys.readouterr().err.strip()
  assert code == 2, (code, err)
  assert len(err.splitlines()) == 1 and re.search(pattern, err), err
  return err

