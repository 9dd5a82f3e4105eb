"""The packages sit in layers, each importing only from the ones below it (see DESIGN.md, Layout):
each package is imported alone in a fresh interpreter and the ``wmjax`` modules it loaded are
checked against the layer order."""

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


def loaded_by(module: str) -> list[str]:
  """The ``wmjax`` modules a fresh interpreter holds after ``import module``."""
  code = (f"import sys, {module}; "
          "print('\\n'.join(sorted(m for m in sys.modules if m.startswith('wmjax'))))")
  run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
  return run.stdout.split()


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


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_only_from_below(package):
  own = layer_of(package)
  loaded = loaded_by(package)
  above = [m for m in loaded if layer_of(m) > own]
  assert not above, f"importing {package} (layer {own}) loads modules of higher layers: {above}"
  forbidden = [m for m in loaded for prefix, banned in FORBIDDEN.items()
               if package.startswith(prefix) for b in banned if m.startswith(b)]
  assert not forbidden, f"importing {package} loads {forbidden}"


def test_data_loads_no_model_code():
  loaded = loaded_by("wmjax.data")
  model_code = [m for m in loaded if _top(m) in (
      "wmjax.nn", "wmjax.diffusion", "wmjax.codecs", "wmjax.rollout", "wmjax.env", "wmjax.model",
      "wmjax.train", "wmjax.eval", "wmjax.tasks")]
  assert not model_code, model_code


def test_eval_loads_nothing_of_train():
  assert not [m for m in loaded_by("wmjax.eval") if m.startswith("wmjax.train")]


def test_every_module_has_a_layer():
  import pathlib
  root = pathlib.Path(__file__).resolve().parents[1] / "wmjax"
  for path in root.rglob("*.py"):
    parts = path.relative_to(root.parent).with_suffix("").parts
    module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    layer_of(module)
