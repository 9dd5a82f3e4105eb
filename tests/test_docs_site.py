"""The documentation site builds as its readers get it: ``mkdocs build --strict`` (broken links
and anchors, pages missing from the navigation, unresolvable cross-references in docstrings
fail it), its API reference has a page for every public module, and the README stays a landing
page."""

import os
import pkgutil
import subprocess
import sys

import pytest
import yaml

import wmjax
from conftest import ROOT

pytestmark = pytest.mark.integration

README_LINES = 300


def public_modules() -> list[str]:
  return sorted(m.name for m in pkgutil.iter_modules(wmjax.__path__) if not m.name.startswith("_"))


@pytest.mark.slow
def test_the_site_builds_strictly(tmp_path):
  env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
  result = subprocess.run(
      [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
      cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
  assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
  # the reference is built from the docstrings: the rollout page documents the rollout function
  page = (tmp_path / "site" / "api" / "rollout" / "index.html").read_text()
  assert 'id="wmjax.rollout.rollout"' in page


def test_the_api_reference_lists_every_public_module():
  config = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=yaml.BaseLoader)
  (api,) = [entry["API reference"] for entry in config["nav"]
            if isinstance(entry, dict) and "API reference" in entry]
  listed = {page for entry in api for page in entry.values()}
  for name in public_modules():
    page = f"api/{name}.md"
    assert page in listed, f"wmjax.{name} has no page in mkdocs.yml's API reference"
    assert f"::: wmjax.{name}" in (ROOT / "docs" / page).read_text()


def test_the_readme_is_a_landing_page():
  lines = (ROOT / "README.md").read_text().splitlines()
  assert len(lines) <= README_LINES, f"README.md has {len(lines)} lines (at most {README_LINES})"
  for page in ("getting-started", "library", "data", "scale", "evaluation", "results", "design"):
    assert f"(docs/{page}.md)" in "\n".join(lines), f"the README does not link docs/{page}.md"
