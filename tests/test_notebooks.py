"""The notebooks run top to bottom (tiny settings), and are stored without outputs."""

import pathlib
import shutil

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.unit
def test_the_three_notebooks_are_there():
  assert [p.stem for p in NOTEBOOKS] == ["keyboard_control", "policy_evaluation", "quickstart"]


@pytest.mark.unit
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_stored_without_outputs(path):
  notebook = nbformat.read(path, as_version=4)
  for cell in notebook.cells:
    if cell.cell_type == "code":
      assert cell.outputs == [] and cell.execution_count is None, f"{path.name}: strip outputs"


# the notebooks on the gridworld share one model: the first to run trains it (its training cell),
# the next loads it (its loading path), as after the README quickstart; the Push-T notebook loads
# the model of the suite's Push-T experiment (conftest.py), as after experiments/pusht/run.py
GRIDWORLD_NOTEBOOKS = ("keyboard_control", "quickstart")


@pytest.fixture(scope="module")
def gridworld_workdir(tmp_path_factory):
  return tmp_path_factory.mktemp("notebook_gridworld") / "model"


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch, gridworld_workdir, request):
  monkeypatch.setenv("WMJAX_NOTEBOOK_SMOKE", "1")
  if path.stem in GRIDWORLD_NOTEBOOKS:
    workdir = gridworld_workdir
  else:  # the notebook writes its evaluation beside the model: a copy
    experiment = request.getfixturevalue("pusht_experiment")
    workdir = shutil.copytree(experiment / "model", tmp_path / "model")
  monkeypatch.setenv("WMJAX_NOTEBOOK_WORKDIR", str(workdir))
  notebook = nbformat.read(path, as_version=4)
  NotebookClient(notebook, timeout=900, kernel_name="python3",
                 resources={"metadata": {"path": str(path.parent)}}).execute()
  outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
  assert not [o for o in outputs if o.output_type == "error"]
  assert any(o.output_type == "display_data" for o in outputs), "no video or table was shown"
