"""Fused GPU kernels (Pallas, Triton backend) for the ST-DiT's bandwidth-bound steps.

Each kernel has a pure-JAX reference beside it and is chosen by a model field that takes one of
:data:`KERNEL_IMPLS`:

``xla``     the plain JAX ops; XLA fuses what it can (every platform; the default).
``pallas``  the fused kernel. On a GPU it is compiled by Triton; elsewhere it runs in Pallas
            interpret mode, exact but slow (for tests and CPU checks, not for speed).
``auto``    ``pallas`` on a GPU, ``xla`` elsewhere.

Under a device mesh (the trainer's ``jax.set_mesh``) a kernel runs once per device through
``shard_map`` (XLA cannot partition a Pallas call): rows are split over the batch axes, and the
MLP's hidden width over ``tensor`` (a LayerNorm's width stays whole).

Kernels: :mod:`wmjax.nn.kernels.mlp` (``model.mlp_kernel``), :mod:`wmjax.nn.kernels.norm`
(``model.norm_kernel``).
"""

from __future__ import annotations

import jax
from jax.sharding import PartitionSpec as P

from wmjax.nn.attention import current_platform, split_axes

__all__ = ["KERNEL_IMPLS", "P", "check_kernel", "interpret", "per_device", "resolve_kernel",
           "split_axes"]

KERNEL_IMPLS = ("xla", "pallas", "auto")


def check_kernel(field: str, name: str) -> None:
  """ValueError for a kernel choice that does not exist (``field`` names the model setting)."""
  if name not in KERNEL_IMPLS:
    raise ValueError(f"{field} must be one of {KERNEL_IMPLS}, got {name!r}")


def resolve_kernel(field: str, name: str, platform: str | None = None) -> str:
  """'xla' or 'pallas': ``auto`` resolved for ``platform`` (default: the platform attention is
  built for, :func:`wmjax.nn.attention.current_platform`)."""
  check_kernel(field, name)
  if name == "auto":
    return "pallas" if (platform or current_platform()) == "gpu" else "xla"
  return name


def interpret(platform: str | None = None) -> bool:
  """Whether a Pallas kernel runs in interpret mode: everywhere but on a GPU."""
  return (platform or current_platform()) != "gpu"


def per_device(fn, in_specs, out_specs):
  """``fn`` run once per device of the current mesh through ``shard_map``, with these specs; ``fn``
  itself off a mesh or when no spec splits anything (every device would see the whole input)."""
  mesh = jax.sharding.get_abstract_mesh()
  if mesh.empty or not any(axis is not None for spec in jax.tree.leaves(
      (in_specs, out_specs), is_leaf=lambda x: isinstance(x, P)) for axis in spec):
    return fn
  return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)
