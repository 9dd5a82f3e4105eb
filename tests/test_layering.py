"""The packages sit in layers, each importing only from the ones below it (docs/design.md,
Layers): each package is imported with no ``wmjax`` module loaded before it, and the ``wmjax``
modules it loaded are checked against the layer order; every import the source names, also those
made when a function runs (an ``import`` inside it, ``importlib.import_module("...")``,
``__import__("...")``), is checked against the order too, and no modules import each other in a
circle."""

import ast
import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration

# Bottom to top; a module belongs to the layer of its longest listed prefix. Push-T's evaluation
# against its simulator uses the generic evaluation tools, so it sits beside them.
LAYERS = (
    ("wmjax", "wmjax.platforms", "wmjax.progress", "wmjax.frames", "wmjax.errors",
     "wmjax.parallel", "wmjax.launch", "wmjax.config", "wmjax.registry"),
    ("wmjax.nn", "wmjax.diffusion", "wmjax.data"),
    ("wmjax.codecs", "wmjax.model", "wmjax.policy"),
    ("wmjax.rollout", "wmjax.env", "wmjax.interactive"),
    ("wmjax.tasks",),
    ("wmjax.train", "wmjax.eval", "wmjax.checkpoints", "wmjax.tasks.pusht.evaluate",
     "wmjax.tasks.metaworld.evaluate"),
    ("wmjax.cli",),
)
# what may not be loaded though it sits lower: eval never imports train, nor a task by name (it
# finds a task's metrics and rewards in wmjax.registry, once an entry point has imported the task
# its config names through wmjax.tasks)
FORBIDDEN = {"wmjax.eval": ("wmjax.train", "wmjax.tasks.")}


def layer_of(module: str) -> int:
  matches = [(len(prefix), i) for i, prefixes in enumerate(LAYERS) for prefix in prefixes
             if module == prefix or module.startswith(prefix + ".")]
  if not matches:
    raise AssertionError(f"{module} is in no layer of tests/test_layering.py: add it")
  return max(matches)[1]


# One interpreter imports the third-party libraries once, then forks a child per package that
# imports it with no ``wmjax`` module loaded: what the child loads of ``wmjax`` is what a fresh
# interpreter loads, without paying for JAX, Flax and TensorFlow a hundred times. The second line
# only saves time (37.6 s -> 16.9 s of children on a 2-core VM): SciPy's and the others' imports,
# which a child would otherwise repeat; a library missing from it costs time, never a wrong answer.
_LOADED_BY = """
import importlib, json, os, sys
import flax.linen, grain, jax, optax, orbax.checkpoint, tensorflow_datasets
import chex, dm_pix, einops, ml_collections, requests, scipy.ndimage, scipy.optimize, scipy.stats
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


# ------------------------------------------------------------------ imports the source names


def _sources() -> dict[str, str]:
  """``{module: path}`` of every module of the package."""
  import pathlib
  root = pathlib.Path(__file__).resolve().parents[1] / "wmjax"
  out = {}
  for path in root.rglob("*.py"):
    parts = path.relative_to(root.parent).with_suffix("").parts
    out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = str(path)
  return out


def _named_imports(tree: ast.AST, package: str) -> list[str]:
  """Every module name an ``import``, ``from ... import`` (relative ones resolved against
  ``package``), ``importlib.import_module("...")`` or ``__import__("...")`` with a literal name
  names, wherever it stands; ``from module import name`` names ``module.name``."""
  names = []
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      names += [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom):
      base = node.module or ""
      if node.level:
        parent = package.split(".")[:len(package.split(".")) - node.level + 1]
        base = ".".join(parent + ([base] if base else []))
      names += [f"{base}.{alias.name}" for alias in node.names]
    elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
          and isinstance(node.args[0].value, str)
          and getattr(node.func, "attr", getattr(node.func, "id", None)) in (
              "import_module", "__import__")):
      names.append(node.args[0].value)
  return names


def import_graph(sources: dict[str, str] | None = None) -> dict[str, set[str]]:
  """``{module: the wmjax modules it imports}`` as the source names them (a name that is no
  module, e.g. a class, counts as the module that holds it)."""
  sources = sources or _sources()
  graph = {}
  for module, path in sources.items():
    with open(path) as f:
      tree = ast.parse(f.read())
    package = module if path.endswith("__init__.py") else module.rpartition(".")[0]
    graph[module] = set()
    for name in _named_imports(tree, package):
      while name and name not in sources:
        name = name.rpartition(".")[0]
      if name and name != module:
        graph[module].add(name)
  return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
  """The sets of two or more modules that import each other in a circle (strongly connected
  components, Tarjan's algorithm)."""
  order, low, stack, found = {}, {}, [], []

  def visit(module):
    order[module] = low[module] = len(order)
    stack.append(module)
    for other in sorted(graph.get(module, ())):
      if other not in order:
        visit(other)
        low[module] = min(low[module], low[other])
      elif other in stack:
        low[module] = min(low[module], order[other])
    if low[module] == order[module]:
      component = []
      while not component or component[-1] != module:
        component.append(stack.pop())
      if len(component) > 1:
        found.append(sorted(component))

  for module in sorted(graph):
    if module not in order:
      visit(module)
  return found


def test_no_import_named_in_the_source_climbs_a_layer():
  """Also what only a function imports when it runs, which the import-time check cannot see."""
  up = [f"{module} -> {other}" for module, others in sorted(import_graph().items())
        for other in sorted(others) if layer_of(other) > layer_of(module)
        or any(module.startswith(prefix) and other.startswith(b)
               for prefix, banned in FORBIDDEN.items() for b in banned)]
  assert not up, f"imports from a lower layer to a higher one: {up}"


def test_no_modules_import_each_other_in_a_circle():
  assert not circles(import_graph())


def test_the_check_sees_imports_made_when_a_function_runs(tmp_path):
  """What the two tests above read: the run-time imports of the old task registry, which closed
  a circle through the data layer."""
  (tmp_path / "registry.py").write_text(
      "import importlib\n"
      "def load():\n"
      "  importlib.import_module('wmjax.tasks')\n"
      "  return __import__('wmjax.train.loop')\n")
  (tmp_path / "tasks.py").write_text("def f():\n  from wmjax.data.sources import dataset_dir\n")
  (tmp_path / "sources.py").write_text("from wmjax import registry\n")
  (tmp_path / "loop.py").write_text("")
  graph = import_graph({"wmjax.registry": str(tmp_path / "registry.py"),
                        "wmjax.tasks": str(tmp_path / "tasks.py"),
                        "wmjax.data.sources": str(tmp_path / "sources.py"),
                        "wmjax.train.loop": str(tmp_path / "loop.py")})
  assert graph["wmjax.registry"] == {"wmjax.tasks", "wmjax.train.loop"}
  assert circles(graph) == [["wmjax.data.sources", "wmjax.registry", "wmjax.tasks"]]


def test_code_below_the_tasks_finds_a_task_once_an_entry_point_imports_it(tmp_path):
  """Nothing below the tasks' layer imports a task: until the task a config names is imported
  (as completing the config does, wmjax.config.import_task), its metrics, rewards and generated datasets
  are unknown, and a generated dataset's error says where its task is named; after, they are
  found, and a generated dataset is made on first use."""
  data = (f"ml_collections.ConfigDict(dict(dataset='gridworld', data_dir={str(tmp_path)!r}, "
          f"gridworld=dict(train_episodes=2, test_episodes=1, episode_length=4)))")
  found = subprocess.run([sys.executable, "-c", (
      "import sys, ml_collections\n"
      "from wmjax import registry\n"
      "from wmjax.config import import_task\n"
      "from wmjax.data.sources import dataset_dir\n"
      "assert registry.frame_metrics_of('pusht') is None and not registry.rewards()\n"
      "try:\n"
      f"  dataset_dir({data})\n"
      "except ValueError as e:\n"
      "  assert 'config.task' in str(e), e\n"
      "assert not [m for m in sys.modules if m.startswith('wmjax.tasks.')]\n"
      "import_task('wmjax.tasks.pusht'); import_task('wmjax.tasks.gridworld')\n"
      "print(registry.frame_metrics_of('pusht').headline, sorted(registry.rewards()))\n"
      f"print(dataset_dir({data}))\n")],
      capture_output=True, text=True)
  assert found.returncode == 0, found.stderr[-3000:]
  lines = found.stdout.strip().splitlines()
  assert [line for line in lines if "['coverage']" in line and line.split()[0] != "['coverage']"]
  made = lines[-1]
  assert made.startswith(str(tmp_path)) and os.path.exists(os.path.join(made, "dataset_info.json"))


def test_a_package_loads_the_same_alone_as_after_others(loaded):
  """A child sees what a fresh interpreter sees, whatever the children before it imported: the
  last package the fixture's interpreter imported, after all the others, against a fresh one."""
  last = PACKAGES[-1]
  fresh = subprocess.run(
      [sys.executable, "-c", f"import sys, {last}; print(sorted(m for m in sys.modules "
       "if m == 'wmjax' or m.startswith('wmjax.')))"], capture_output=True, text=True, check=True)
  assert len(loaded[last]) > 1 and str(loaded[last]) == fresh.stdout.strip()


def test_the_design_document_lists_these_layers():
  """docs/design.md, Layers, is the table above in words: the same layers, bottom to top."""
  import pathlib
  import re
  text = (pathlib.Path(__file__).resolve().parents[1] / "docs" / "design.md").read_text()
  section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
  items = re.findall(r"^\d+\. .*(?:\n   .*)*", section, re.MULTILINE)
  stated = [{name if name == "wmjax" else f"wmjax.{name}" for name in re.findall(r"`([\w.]+)`", item)}
            for item in items]
  assert stated == [set(layer) for layer in LAYERS]


def test_every_module_has_a_layer():
  for module in _sources():
    layer_of(module)
