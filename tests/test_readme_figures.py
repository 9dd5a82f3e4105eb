"""The measured figures of the README and the documentation pages are the results files' own:
every figure with a decimal point in a paragraph of README.md or docs/*.md (but the generated
docs/results.md, which tests/test_results_page.py regenerates from its JSON) that cites a results
file (``benchmarks/RESULTS.md``,
``experiments/<study>/RESULTS.md`` or ``experiments/<study>/``) is a number of one of the files it
cites, so that no figure is quoted without its measurement or edited away from it."""

import re

import pytest

from conftest import ROOT

pytestmark = pytest.mark.unit

CITATION = re.compile(r"\b(benchmarks|experiments/[\w-]+)/(?:RESULTS\.md)?")
# a figure with a decimal point, not part of a version (0.11.2) or a name
FIGURE = re.compile(r"(?<![\w.])-?\d+\.\d+(?:e-?\d+)?(?![\w.]*\d)")
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e-?\d+)?")


def _prose(text: str) -> str:
  """``text`` with its fenced code blocks left out and Unicode minus signs as '-'."""
  return re.sub(r"```.*?```", "", text, flags=re.S).replace("\u2212", "-")


def _paragraphs(text: str) -> list[str]:
  return [p for p in re.split(r"\n\s*\n", _prose(text)) if p.strip()]


def _cited_files(paragraph: str) -> list:
  """The results files a paragraph cites (``experiments/<study>/`` means its RESULTS.md)."""
  return sorted({ROOT / match / "RESULTS.md" for match in CITATION.findall(paragraph)})


def _numbers(path) -> set[float]:
  return {float(n) for n in NUMBER.findall(_prose(path.read_text()))}


def _documents() -> list:
  """README.md and the documentation pages written by hand."""
  pages = sorted(p for p in (ROOT / "docs").rglob("*.md") if p.name != "results.md")
  return [ROOT / "README.md"] + pages


def test_every_figure_the_documents_quote_is_in_the_results_file_it_cites():
  checked, unfound = 0, []
  paragraphs = [p for document in _documents() for p in _paragraphs(document.read_text())]
  for paragraph in paragraphs:
    files = _cited_files(paragraph)
    if not files:
      continue
    assert all(f.is_file() for f in files), f"a document cites missing files: {files}"
    known = set().union(*(_numbers(f) for f in files))
    for figure in FIGURE.findall(paragraph):
      checked += 1
      if float(figure) not in known:
        unfound.append(f"{figure} (in {[str(f.relative_to(ROOT)) for f in files]}): "
                       f"{' '.join(paragraph.split())[:120]}...")
  assert checked >= 20, f"only {checked} figures found: has the citation form changed?"
  assert not unfound, "figures no cited results file holds:\n" + "\n".join(unfound)


def test_a_figure_missing_from_its_file_is_caught(tmp_path):
  """The check itself: a figure is a number of a file, a version or a name is no figure."""
  assert FIGURE.findall("41.7 % MFU on jax 0.11.2, fp8 e4m3, -0.23 and 2.4e-6; DDIM 1-2") == [
      "41.7", "-0.23", "2.4e-6"]
  results = tmp_path / "RESULTS.md"
  results.write_text("| run | 41.70 | \u22120.23 | 2.4e-06 |\n```\n9.5\n```\n")
  assert {41.7, -0.23, 2.4e-6} <= _numbers(results) and 9.5 not in _numbers(results)
  assert _cited_files("as `benchmarks/RESULTS.md` and `experiments/pusht/` say") == [
      ROOT / "benchmarks" / "RESULTS.md", ROOT / "experiments" / "pusht" / "RESULTS.md"]
