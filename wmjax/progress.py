"""Progress of a long loop that a terminal and a log file can both read.

On a terminal a tqdm bar; anywhere else (a batch job's log, ``nohup``, CI) one plain line on
stdout every tenth of the work and at its end, since carriage-return updates of a bar make one
ever-growing line there::

    policy expert:0.2 in the world model: 12/24 episodes, elapsed 0:41, ETA 0:41
"""

from __future__ import annotations

import sys
import time


def clock(seconds: float) -> str:
  """``seconds`` as ``M:SS`` (minutes unbounded)."""
  return f"{int(seconds // 60)}:{int(seconds % 60):02d}"


def plain() -> bool:
  """Whether progress is written as plain lines: stderr, where a bar would go, is no terminal."""
  return not sys.stderr.isatty()


class Progress:
  """``total`` units of work called ``unit`` (plural), done in a loop named ``what``; use as a
  context manager and call :meth:`update` after each unit or batch of units."""

  def __init__(self, what: str, total: int, unit: str = "steps"):
    self.what, self.total, self.unit, self.done = what, max(int(total), 1), unit, 0
    self.began = time.perf_counter()
    self._every = max(1, self.total // 10)
    self._next = self._every
    self._bar = None
    if not plain():
      from tqdm import tqdm
      self._bar = tqdm(total=self.total, desc=what, unit=unit.rstrip("s") or unit,
                       dynamic_ncols=True, leave=False)

  def line(self) -> str:
    """The plain line of the progress so far."""
    elapsed = time.perf_counter() - self.began
    left = (self.total - self.done) * elapsed / max(self.done, 1)
    return (f"{self.what}: {self.done}/{self.total} {self.unit}, elapsed {clock(elapsed)}, "
            f"ETA {clock(left)}")

  def update(self, count: int = 1) -> None:
    self.done = min(self.done + count, self.total)
    if self._bar is not None:
      self._bar.update(count)
    elif self.done >= self._next or self.done == self.total:
      print(self.line(), flush=True)
      self._next = (self.done // self._every + 1) * self._every

  def close(self) -> None:
    if self._bar is not None:
      self._bar.close()

  def __enter__(self) -> Progress:
    return self

  def __exit__(self, *exc) -> None:
    self.close()
