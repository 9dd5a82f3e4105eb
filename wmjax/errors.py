"""Errors a command reports in one line, with the way out: why a run stopped, why a checkpoint
cannot be written or read, and what orbax or the OS said, in short."""

from __future__ import annotations

import errno
import os
import sys


class RunError(RuntimeError):
  """A training run cannot go on, for a reason its message states with the way out; the command
  line prints the message alone, without a traceback."""


class CheckpointError(RunError):
  """A checkpoint cannot be written or read back."""


def describe_error(error: BaseException, limit: int = 500) -> str:
  """``Type: first line of the message`` of an exception, or of the ``OSError`` behind it (a full
  disk is reported as such however deep orbax or tensorstore wrapped it)."""
  seen, cause = set(), error
  while cause is not None and id(cause) not in seen:
    seen.add(id(cause))
    if isinstance(cause, OSError) and cause.errno is not None:
      error = cause
      break
    cause = cause.__cause__ or cause.__context__
  if isinstance(error, OSError) and error.errno is not None:
    text = f"{os.strerror(error.errno)} ({errno.errorcode.get(error.errno, error.errno)})"
    if error.filename:
      text += f": {error.filename}"
  else:
    lines = str(error).strip().splitlines()
    first = lines[0].split(" [tensorstore_spec=")[0] if lines else ""
    text = f"{type(error).__name__}: {first}".rstrip(": ")
  if "RESOURCE_EXHAUSTED" in text or "No space left" in text:
    text = "the disk is full (" + text + ")"
  return text if len(text) <= limit else text[:limit - 3] + "..."


def ignore_closed_loop_callbacks() -> None:
  """After a failed read, tensorstore still completes the other reads of the batch and hands
  their results to orbax's event loop, which the failure has closed: every one of them would
  print a ``RuntimeError: Event loop is closed`` traceback (hundreds, burying the real error,
  which is reported on its own). Drop exactly those; other unraisable errors go through."""
  previous = sys.unraisablehook
  if getattr(previous, "_wmjax", False):
    return

  def hook(unraisable):
    value = unraisable.exc_value
    if isinstance(value, RuntimeError) and str(value) == "Event loop is closed":
      return
    previous(unraisable)

  hook._wmjax = True
  sys.unraisablehook = hook
