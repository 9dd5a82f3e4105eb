"""The packages sit in layers, each importing only from the ones below it (see DESIGN.md, Layout):
each package is imported with no ``wmjax`` module loaded before it, and the ``wmjax`` modules it
loaded are checked against the layer order."""

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration

# Bottom to top; a module belongs to the layer of its longest listed prefix. Push-T's evaluation
# against its simulator uses the generic evaluation tools, so it sits beside them.
LAYERS = (
    ("wmjax", "wmjax.frames", "wmjax.errors", "wmjax.parallel", "wmjax.launch", "wmjax.config"),
    ("wmjax.nn", "wmjax.diffusion", "wmjax.data"),
    ("wmjax.codecs", "wmjax.model"),
    ("wmjax.rollout", "wmjax.env", "wmjax.interactive"),
    ("wmjax.tasks",),
    ("wmjax.train", "wmjax.eval", "wmjax.tasks.pusht.evaluate"),
    ("wmjax.cli",),
)
# what may not be loaded even though it sits lower: eval never imports train
FORBIDDEN = {"wmjax.eval": ("wmjax.train",)}


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


# every package, and the modules that load the most of their package
PACKAGES = ["wmjax.frames", "wmjax.errors", "wmjax.parallel", "wmjax.config", "wmjax.nn",
            "wmjax.diffusion", "wmjax.data.pipeline", "wmjax.data.latents", "wmjax.codecs",
            "wmjax.model", "wmjax.rollout", "wmjax.env", "wmjax.interactive", "wmjax.tasks",
            "wmjax.tasks.pusht.evaluate", "wmjax.eval.evaluate", "wmjax.eval.rewards",
            "wmjax.eval.policy_eval", "wmjax.eval.user_rollout", "wmjax.train.loop",
            "wmjax.train.info", "wmjax.train.encode", "wmjax.cli", "wmjax.cli.train",
            "wmjax.cli.evaluate", "wmjax.cli.rollout", "wmjax.cli.pusht", "wmjax.cli.launch",
            "wmjax.cli.info", "wmjax.cli.compile", "wmjax.cli.data"]


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


def test_eval_loads_nothing_of_train(loaded):
  assert not [m for m in loaded["wmjax.eval"] if m.startswith("wmjax.train")]


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
