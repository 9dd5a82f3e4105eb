"""Progress that a log file can read: plain lines where stderr is no terminal, a bar where it is."""

import io

import pytest

from wmjax import progress

pytestmark = pytest.mark.unit


def test_plain_lines_every_tenth_and_at_the_end(capsys, monkeypatch):
  monkeypatch.setattr(progress, "plain", lambda: True)
  with progress.Progress("policy evaluation", 25, "episodes") as tracker:
    for _ in range(25):
      tracker.update()
  lines = capsys.readouterr().out.splitlines()
  assert [line.split(",")[0] for line in lines] == [
      f"policy evaluation: {n}/25 episodes" for n in (2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24,
                                                      25)]
  assert all("elapsed 0:0" in line and "ETA " in line for line in lines)
  assert "\r" not in "".join(lines)


def test_a_batch_of_units_and_overshoot(capsys, monkeypatch):
  monkeypatch.setattr(progress, "plain", lambda: True)
  tracker = progress.Progress("evaluate long", 7, "trajectories")
  tracker.update(4)
  tracker.update(4)  # a padded last batch counts no more than the total
  assert capsys.readouterr().out.splitlines()[-1].startswith("evaluate long: 7/7 trajectories")


def test_a_terminal_gets_a_bar_and_no_lines(capsys, monkeypatch):
  monkeypatch.setattr(progress, "plain", lambda: False)
  stream = io.StringIO()
  monkeypatch.setattr("sys.stderr", stream)
  with progress.Progress("planning", 3, "settings") as tracker:
    tracker.update(3)
  assert capsys.readouterr().out == "" and "planning" in stream.getvalue()


def test_clock():
  assert progress.clock(0) == "0:00" and progress.clock(61.9) == "1:01"
  assert progress.clock(3725) == "62:05"
