"""Device meshes and global batches.

Batches are sharded over the batch mesh axes ``('data', 'fsdp')``: each process feeds its own
slice and :func:`global_batch` assembles the slices into global ``jax.Array``s.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXES = ("data", "fsdp")


def batch_sharding(mesh: Mesh, batch_axes: Sequence[str] = BATCH_AXES) -> NamedSharding:
  """Leading (batch) axis sharded over ``batch_axes``, every other axis replicated."""
  return NamedSharding(mesh, PartitionSpec(tuple(a for a in batch_axes if a in mesh.axis_names)))


def global_batch(local: Mapping[str, Any], mesh: Mesh,
                 batch_axes: Sequence[str] = BATCH_AXES) -> dict[str, jax.Array]:
  """This process's batch slice (numpy, leading batch axis) -> global arrays on ``mesh``.

  Numeric entries only: strings (instructions) stay on the host and are left out. The global
  batch is ``process_count`` times the local one.
  """
  sharding = batch_sharding(mesh, batch_axes)
  shards = int(np.prod([mesh.shape[a] for a in batch_axes if a in mesh.axis_names]))
  out = {}
  for key, value in local.items():
    value = np.asarray(value)
    if value.dtype.kind not in "biuf":
      continue
    global_size = value.shape[0] * jax.process_count()
    if global_size % shards:
      raise ValueError(f"global batch {global_size} is not divisible by the {shards} batch "
                       f"shards of the mesh {dict(mesh.shape)}")
    out[key] = jax.make_array_from_process_local_data(sharding, value)
  return out
