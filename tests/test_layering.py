"""The packages sit in layers, each importing only from the ones below it (see DESIGN.md, Layout):
each package is imported with no ``wmjax`` module loaded before it, and the ``wmjax`` modules it
loaded are checked against the layer order."""

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration

# Bottom to top; a module belongs to the layer of its longest listed prefix. Push-T's evaluation
# against its simulator uses the generic evaluation tools, so it sits beside them.
LAYERS = (
    ("wmjax", "wmjax.frames", "wmjax.errors", "wmjax.parallel", "wmjax.launch", "wmjax.config",
     "wmjax.registry"),
    ("wmjax.nn", "wmjax.diffusion", "wmjax.data"),
    ("wmjax.codecs", "wmjax.model"),
    ("wmjax.rollout", "wmjax.env", "wmjax.interactive"),
    ("wmjax.tasks",),
    ("wmjax.train", "wmjax.eval", "wmjax.checkpoints", "wmjax.tasks.pusht.evaluate"),
    ("wmjax.cli",),
)
# what may not be loaded though it sits lower: eval never imports train, and finds the tasks
# through wmjax.registry (which loads them when first asked, not when imported)
FORBIDDEN = {"wmjax.eval": ("wmjax.train", "wmjax.tasks")}


def layer_of(module: str) -> int:
  matches = [(len(prefix), i) for i, prefixes in enumerate(LAYERS) for prefix in prefixes
             if module == prefix or module.startswith(prefix + ".")]
  if not matches:
    raise AssertionError(f"{module} is in no layer of tests/test_layering.py: add it")
  return max(matches)[1]


# One interpreter imports the third-party libraries once, then forks a child per package that
# imports it with no ``wmjax`` module loaded: what the child loads of ``wmjax`` is what a fresh
# interpreter loads, without paying for JAX, Flax and TensorFlow 30 times.
_LOADED_BY = """
import importlib, json, os, sys
import flax.linen, grain, jax, optax, orbax.checkpoint, tensorflow_datasets
loaded = {}
for module in sys.argv[1:]:
  read, write = os.pipe()
  if os.fork() == 0:
    os.close(read)
    importlib.import_module(module)
    names = sorted(m for m in sys.modules if m == "wmjax" or m.startswith("wmjax."))
    os.write(write, json.dumps(names).encode())
    os._exit(0)
  os.close(write)
  with os.fdopen(read) as pipe:
    text = pipe.read()
  _, status = os.wait()
  if status or not text:
    sys.exit(f"importing {module} failed (status {status})")
  loaded[module] = json.loads(text)
print(json.dumps(loaded))
"""


def loaded_by(*modules: str) -> dict[str, list[str]]:
  """The ``wmjax`` modules held after ``import module``, for each module, none loaded before."""
  run = subprocess.run([sys.executable, "-c", _LOADED_BY, *modules], capture_output=True,
                       text=True)
  if run.returncode:
    raise AssertionError(run.stderr[-3000:])
  return json.loads(run.stdout.splitlines()[-1])


def _top(module: str) -> str:
  return ".".join(module.split(".")[:2])


def _every_module() -> list[str]:
  import pkgutil

  import wmjax
  return ["wmjax"] + sorted(m.name for m in pkgutil.walk_packages(wmjax.__path__, "wmjax.")
                            if m.name != "wmjax.cli.__main__")  # runs the command line


# every module of the package
PACKAGES = _every_module()


@pytest.fixture(scope="module")
def loaded():
  return loaded_by(*PACKAGES, "wmjax.data", "wmjax.eval")


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_only_from_below(package, loaded):
  own = layer_of(package)
  loaded = loaded[package]
  above = [m for m in loaded if layer_of(m) > own]
  assert not above, f"importing {package} (layer {own}) loads modules of higher layers: {above}"
  forbidden = [m for m in loaded for prefix, banned in FORBIDDEN.items()
               if package.startswith(prefix) for b in banned if m.startswith(b)]
  assert not forbidden, f"importing {package} loads {forbidden}"


def test_data_loads_no_model_code(loaded):
  model_code = [m for m in loaded["wmjax.data"] if _top(m) in (
      "wmjax.nn", "wmjax.diffusion", "wmjax.codecs", "wmjax.rollout", "wmjax.env", "wmjax.model",
      "wmjax.train", "wmjax.eval", "wmjax.tasks")]
  assert not model_code, model_code


def test_eval_loads_neither_train_nor_the_tasks(loaded):
  assert not [m for m in loaded["wmjax.eval"] if m.startswith(("wmjax.train", "wmjax.tasks"))]


def test_the_registry_finds_the_built_in_tasks_without_their_import(tmp_path):
  """Code below the tasks' layer never imports them; a lookup loads them: task metrics,
  rewards, and a generated dataset's directory (made on first use)."""
  found = subprocess.run([sys.executable, "-c", (
      "import sys; from wmjax import registry; assert 'wmjax.tasks' not in sys.modules; "
      "print(registry.frame_metrics_of('pusht').headline, sorted(registry.rewards()))")],
      capture_output=True, text=True, check=True).stdout.split()
  assert found[0] and "coverage" in " ".join(found[1:])
  made = subprocess.run([sys.executable, "-c", (
      "import sys, ml_collections; from wmjax.data.sources import dataset_dir; "
      "assert 'wmjax.tasks' not in sys.modules; "
      "print(dataset_dir(ml_collections.ConfigDict(dict(dataset='gridworld', "
      f"data_dir={str(tmp_path)!r}, gridworld=dict(train_episodes=2, test_episodes=1, "
      "episode_length=4)))))")],
      capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
  assert made.startswith(str(tmp_path)) and os.path.exists(os.path.join(made, "dataset_info.json"))


def test_a_package_loads_the_same_alone_as_after_others():
  """A child sees what a fresh interpreter sees, whatever the children before it imported."""
  alone = loaded_by("wmjax.cli.pusht")["wmjax.cli.pusht"]
  assert alone == loaded_by("wmjax.train.loop", "wmjax.cli.pusht")["wmjax.cli.pusht"]
  fresh = subprocess.run(
      [sys.executable, "-c", "import sys, wmjax.cli.pusht; print(sorted(m for m in sys.modules "
       "if m == 'wmjax' or m.startswith('wmjax.')))"], capture_output=True, text=True, check=True)
  assert str(alone) == fresh.stdout.strip()


def test_every_module_has_a_layer():
  import pathlib
  root = pathlib.Path(__file__).resolve().parents[1] / "wmjax"
  for path in root.rglob("*.py"):
    parts = path.relative_to(root.parent).with_suffix("").parts
    module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    layer_of(module)
