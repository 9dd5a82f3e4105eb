"""The files of a training workdir that are not checkpoints: the lock that keeps a second trainer
out, the metrics log cut back to the step a run resumes from, and the record of config changes
accepted on resume; a workdir a run created and left empty is removed.

The lock is ``WORKDIR/train.lock``, held with ``flock`` by the process that trains and holding its
pid, host and start time. The kernel drops the lock when that process dies (even by ``kill -9``),
so a stale lock file is simply taken over; where the filesystem has no ``flock``, a lock whose
pid is no longer running on this host is stale.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import time
from typing import Iterator

from wmjax.errors import RunError

LOCK_NAME = "train.lock"
METRICS_LOG = "metrics.jsonl"
CONFIG_CHANGES = "config_changes.jsonl"


class WorkdirLockedError(RunError):
  """Another process is training in the same workdir."""


def make_workdir(workdir: str) -> str | None:
  """Create ``workdir`` and its missing parents; the outermost directory this created, or None
  when ``workdir`` existed."""
  created, path = None, os.path.abspath(workdir)
  while not os.path.exists(path):
    created, path = path, os.path.dirname(path)
  os.makedirs(workdir, exist_ok=True)
  return created


def remove_empty_dirs(top: str) -> None:
  """Remove the empty directories under ``top``, then ``top`` itself if that left it empty: a
  run that stopped before writing anything leaves no trace. Files are never removed."""
  for directory, _, _ in os.walk(top, topdown=False):
    try:
      os.rmdir(directory)
    except OSError:  # not empty
      pass


def _process_start(pid: int) -> str | None:
  """Start time of a process in clock ticks since boot (tells a reused pid apart), or None."""
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().rsplit(")", 1)[1].split()[19]
  except (OSError, IndexError):
    return None


def _running(holder: dict) -> bool:
  """Whether the process a lock record names still runs (on this host; another host's process
  is assumed to)."""
  if holder.get("host") != socket.gethostname():
    return True
  pid = int(holder.get("pid", -1))
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:
    pass
  start = _process_start(pid)
  return start is None or holder.get("start") in (None, start)


class WorkdirLock:
  """``acquire()`` or :class:`WorkdirLockedError` naming the holder; ``release()`` removes it."""

  def __init__(self, workdir: str):
    self.workdir = workdir
    self.path = os.path.join(workdir, LOCK_NAME)
    self._fd: int | None = None

  def _read(self) -> dict:
    try:
      with open(self.path) as f:
        return json.loads(f.read() or "{}")
    except (OSError, ValueError):
      return {}

  def _refuse(self, holder: dict):
    who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}, training since "
           f"{holder.get('since', '?')}")
    raise WorkdirLockedError(
        f"{self.workdir} is in use by another `wmjax train` ({who}); two trainers in one workdir "
        f"would overwrite each other's checkpoints and logs. Wait for it, stop it, or train in "
        f"another --workdir (if that process is gone on another host, delete {self.path}).")

  def acquire(self) -> None:
    record = {"pid": os.getpid(), "host": socket.gethostname(),
              "start": _process_start(os.getpid()), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    for _ in range(5):
      fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
      try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      except OSError as e:
        os.close(fd)
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
          self._refuse(self._read())
        # no flock on this filesystem: judge by the recorded process
        holder = self._read()
        if holder and _running(holder) and holder.get("pid") != os.getpid():
          self._refuse(holder)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
      else:
        try:  # the holder may have removed the file between our open and flock
          if os.fstat(fd).st_ino != os.stat(self.path).st_ino:
            os.close(fd)
            continue
        except FileNotFoundError:
          os.close(fd)
          continue
      os.ftruncate(fd, 0)
      os.write(fd, (json.dumps(record) + "\n").encode())
      os.fsync(fd)
      self._fd = fd
      return
    raise WorkdirLockedError(f"could not take {self.path}: other processes keep replacing it")

  def release(self) -> None:
    if self._fd is None:
      return
    try:
      os.unlink(self.path)
    except FileNotFoundError:
      pass
    os.close(self._fd)  # drops the flock
    self._fd = None


@contextlib.contextmanager
def claimed(workdir: str, lock: bool = True) -> Iterator[str]:
  """``workdir`` as an absolute path, made if missing and, with ``lock`` (the process that
  trains), held under its :class:`WorkdirLock` while the block runs; what this made is removed
  again if the block fails before writing anything there (a config or data error)."""
  workdir = os.path.abspath(os.path.expanduser(workdir))
  created = make_workdir(workdir)
  holder = WorkdirLock(workdir) if lock else None
  try:
    if holder is not None:
      holder.acquire()
    try:
      yield workdir
    finally:
      if holder is not None:
        holder.release()
  except BaseException:
    if created is not None:
      remove_empty_dirs(created)
    raise


def truncate_metrics_log(workdir: str, step: int) -> None:
  """Keep only the rows of ``metrics.jsonl`` up to ``step`` (the step a run resumes from; 0 for a
  fresh start), so that a resumed run logs every step once. A row cut short by a kill is
  dropped."""
  path = os.path.join(workdir, METRICS_LOG)
  if not os.path.exists(path):
    return
  kept = []
  with open(path) as f:
    for line in f:
      try:
        row = json.loads(line)
      except ValueError:
        continue
      if isinstance(row, dict) and row.get("step", 0) <= step:
        kept.append(line if line.endswith("\n") else line + "\n")
  temporary = path + ".tmp"
  with open(temporary, "w") as f:
    f.writelines(kept)
  os.replace(temporary, path)


def record_config_changes(workdir: str, step: int, changes: dict, accepted_by: dict) -> None:
  """Append the config changes a resumed run accepted to ``config_changes.jsonl``."""
  row = {"step": step, "time": time.strftime("%Y-%m-%d %H:%M:%S"),
         "changes": {k: {"checkpoint": old, "now": new, "accepted": accepted_by[k]}
                     for k, (old, new) in changes.items()}}
  with open(os.path.join(workdir, CONFIG_CHANGES), "a") as f:
    f.write(json.dumps(row) + "\n")
