"""docs/results.md is what docs/make_results.py writes from the committed results JSON: a page
edited by hand, or data changed without regenerating it, fails here. Only the Markdown is
compared; of the plots, that every image the page links is there and is a PNG."""

import importlib.util
import re

import pytest

from conftest import ROOT

pytestmark = pytest.mark.unit

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _make_results():
  spec = importlib.util.spec_from_file_location("make_results", ROOT / "docs" / "make_results.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def _linked_images(page: str) -> list[str]:
  return re.findall(r"!\[[^\]]*\]\(([^)]+)\)", page)


def test_the_committed_page_is_what_the_script_writes_from_the_json(tmp_path):
  written = _make_results().write_results_page(tmp_path)
  assert written[0] == tmp_path / "results.md"
  page = written[0].read_text()
  committed = (ROOT / "docs" / "results.md").read_text()
  assert page == committed, (
      "docs/results.md differs from what docs/make_results.py writes from the results JSON: "
      "run `python docs/make_results.py` and commit the page and its plots")
  images = _linked_images(page)
  assert len(images) >= 5 and set(written[1:]) == {tmp_path / image for image in images}
  for folder in (tmp_path, ROOT / "docs"):
    for image in images:
      data = (folder / image).read_bytes()
      assert data.startswith(PNG_SIGNATURE) and len(data) > 1000, f"{folder / image}"
