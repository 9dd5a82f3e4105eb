"""Local multi-process launcher: N copies of a command joined by ``jax.distributed``.

Each copy gets ``--coordinator_address 127.0.0.1:PORT --num_processes N --process_id I``
appended (the flags ``wmjax train`` takes), and its own devices: on CPU ``--devices_per_process``
simulated host devices (gloo collectives), on GPU its own slice of the GPUs through
``CUDA_VISIBLE_DEVICES``. Output lines are prefixed with the process index. When one process
fails the others are stopped, and the launcher returns the first non-zero exit code.

  wmjax launch --num_processes 2 -- train --config configs/gridworld.py --workdir DIR
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from typing import Sequence


def free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def process_env(index: int, platform: str, devices_per_process: int) -> dict[str, str]:
  """The environment of process ``index``: its devices and platform."""
  env = dict(os.environ)
  if platform == "cpu":
    env["JAX_PLATFORMS"] = "cpu"
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(flags + [
        f"--xla_force_host_platform_device_count={devices_per_process}"])
  elif platform == "gpu":
    first = index * devices_per_process
    env["CUDA_VISIBLE_DEVICES"] = ",".join(str(first + k) for k in range(devices_per_process))
  else:
    raise ValueError(f"platform must be 'cpu' or 'gpu', got {platform!r}")
  return env


def _relay(index: int, stream) -> None:
  for line in stream:
    sys.stdout.write(f"[{index}] {line}")
    sys.stdout.flush()


def launch_local(command: Sequence[str], num_processes: int, *, platform: str = "cpu",
                 devices_per_process: int = 1, port: int | None = None,
                 timeout: float | None = None) -> int:
  """Run ``command`` as ``num_processes`` cooperating processes; returns the exit code."""
  if num_processes < 1 or devices_per_process < 1:
    raise ValueError(f"need num_processes >= 1 and devices_per_process >= 1, got "
                     f"{num_processes} and {devices_per_process}")
  address = f"127.0.0.1:{port or free_port()}"
  processes, relays = [], []
  for index in range(num_processes):
    flags = ["--coordinator_address", address, "--num_processes", str(num_processes),
             "--process_id", str(index)]
    process = subprocess.Popen(list(command) + flags,
                               env=process_env(index, platform, devices_per_process),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    relay = threading.Thread(target=_relay, args=(index, process.stdout), daemon=True)
    relay.start()
    processes.append(process)
    relays.append(relay)
  deadline = None if timeout is None else time.monotonic() + timeout
  code = 0
  try:
    while any([p.poll() is None for p in processes]):  # a list: poll every process
      failed = [p.returncode for p in processes if p.returncode not in (None, 0)]
      if failed or (deadline is not None and time.monotonic() > deadline):
        code = failed[0] if failed else 124
        break
      time.sleep(0.2)
    else:
      code = next((p.returncode for p in processes if p.returncode != 0), 0)
  finally:
    for process in processes:
      if process.poll() is None:
        process.terminate()
    for process in processes:
      try:
        process.wait(timeout=30)
      except subprocess.TimeoutExpired:
        process.kill()
    for relay in relays:
      relay.join(timeout=5)
  return code
