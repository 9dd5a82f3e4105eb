"""Device meshes, logical-axis sharding rules and global batches.

Parameters carry logical axis names (``wmjax.nn.layers``); :data:`LOGICAL_RULES` maps them onto
the ``('data', 'fsdp', 'tensor')`` mesh. Batches are sharded over the batch mesh axes
``('data', 'fsdp')``: each process feeds its own slice and :func:`global_batch` assembles the
slices into global ``jax.Array``s.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Mapping, Sequence

import flax.linen as nn
import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec

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
  out = {}
  for key, value in local.items():
    value = np.asarray(value)
    if value.dtype.kind not in "biuf":
      continue
    check_batch_divisible(value.shape[0] * jax.process_count(), mesh, batch_axes=batch_axes)
    out[key] = jax.make_array_from_process_local_data(sharding, value)
  return out


def check_batch_divisible(batch: int, mesh: Mesh, micro_batches: int = 1, processes: int = 1,
                          what: str = "global batch",
                          batch_axes: Sequence[str] = BATCH_AXES) -> None:
  """ValueError unless a global batch of ``batch`` examples splits evenly over the batch axes of
  ``mesh`` (the data-parallel size), each shard into ``micro_batches`` gradient-accumulation
  micro-batches, and over ``processes`` feeding processes. The one home of this check: the
  train step before it compiles or runs (:func:`wmjax.train.step.check_batch_shapes`) and
  :func:`global_batch` call it."""
  axes = [a for a in batch_axes if a in mesh.axis_names]
  data_parallel = int(np.prod([mesh.shape[a] for a in axes]))
  multiple = math.lcm(data_parallel * micro_batches, processes)
  if batch % multiple == 0:
    return
  factors = f"the data-parallel size {data_parallel}"
  if micro_batches > 1:
    factors += f" x {micro_batches} micro-batches (optim.grad_accum)"
  if processes > 1:
    factors += f" and the {processes} processes"
  layout = " x ".join(axes) + " = " + " x ".join(str(mesh.shape[a]) for a in axes)
  raise ValueError(f"{what} {batch} is not divisible by {factors} (mesh {layout}): expected a "
                   f"multiple of {multiple}, got {batch}")


# ----------------------------------------------------------------------------- meshes and rules

MESH_AXES = ("data", "fsdp", "tensor")

# Logical parameter / activation axes -> mesh axes: FSDP shards the model width, tensor
# parallelism the heads and MLP hidden units; stacked layers and small axes stay replicated.
LOGICAL_RULES = (
    ("batch", ("data", "fsdp")),
    ("layers", None),
    ("embed", "fsdp"),
    ("mlp", "tensor"),
    ("heads", "tensor"),
    ("modulation", "tensor"),
    ("kv", None),
    ("freq", None),
    ("action", None),
    ("patch", None),
    # activations [B, T, P, D] at block boundaries (wmjax.nn.layers.ACTIVATION_AXES): the batch
    # is split over the data-parallel axes, the rest kept whole, so that FSDP's sharded weights
    # never lay activations out along the width
    ("act_batch", ("data", "fsdp")),
    ("act_frames", None),
    ("act_patches", None),
    ("act_embed", None),
)


def make_mesh(shape: Sequence[int], devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A ``('data', 'fsdp', 'tensor')`` mesh with Auto axis types (GSPMD); one -1 takes the rest."""
  devices = list(devices) if devices is not None else jax.devices()
  shape = list(shape)
  if len(shape) != 3:
    raise ValueError(f"mesh shape must give (data, fsdp, tensor), got {shape}")
  if shape.count(-1) > 1:
    raise ValueError(f"at most one mesh axis may be -1, got {shape}")
  if -1 in shape:
    known = int(np.prod([s for s in shape if s != -1]))
    if len(devices) % known:
      raise ValueError(f"{len(devices)} devices do not divide into mesh {shape}")
    shape[shape.index(-1)] = len(devices) // known
  if int(np.prod(shape)) != len(devices):
    raise ValueError(f"mesh {tuple(shape)} needs {int(np.prod(shape))} devices, "
                     f"{len(devices)} are available")
  return jax.make_mesh(tuple(shape), MESH_AXES, axis_types=(AxisType.Auto,) * 3,
                       devices=devices)


def logical_shardings(boxed_tree: Any, mesh: Mesh, rules=LOGICAL_RULES) -> Any:
  """NamedShardings for a tree whose leaves may carry logical axis names (``nn.Partitioned``);
  the result has the tree's unboxed structure, unnamed leaves replicated."""
  specs = nn.get_partition_spec(boxed_tree)
  return nn.logical_to_mesh_sharding(specs, mesh, rules)


_AXIS_SOURCES = {"heads": "model.num_heads", "embed": "model.hidden_size",
                 "mlp": "model.hidden_size x model.mlp_ratio",
                 "modulation": "model.hidden_size x 6"}


def check_shardable(boxed_tree: Any, mesh: Mesh, rules=LOGICAL_RULES) -> None:
  """ValueError, before anything compiles, naming the first parameter whose dimension the mesh
  axes its logical axis maps to cannot split evenly (e.g. 4 heads over a 3-way ``tensor``)."""
  rule_of = dict(rules)
  leaves = jax.tree_util.tree_leaves_with_path(
      boxed_tree, is_leaf=lambda x: isinstance(x, nn.LogicallyPartitioned))
  for path, leaf in leaves:
    if not isinstance(leaf, nn.LogicallyPartitioned):
      continue
    for size, name in zip(leaf.value.shape, leaf.names):
      axes = rule_of.get(name)
      axes = (axes,) if isinstance(axes, str) else tuple(axes or ())
      ways = int(np.prod([mesh.shape[a] for a in axes if a in mesh.shape]))
      if ways > 1 and size % ways:
        source = f" ({_AXIS_SOURCES[name]})" if name in _AXIS_SOURCES else ""
        raise ValueError(
            f"the mesh {dict(mesh.shape)} cannot shard the model: parameter "
            f"{jax.tree_util.keystr(path)} has {size} along its '{name}' axis{source}, which "
            f"the mesh's {' x '.join(axes)} axis ({ways}) does not divide; choose config.mesh "
            f"(data, fsdp, tensor) so that it does")


def local_data_mesh() -> jax.sharding.Mesh:
  """A 1-D ``('data',)`` mesh over this process's devices, for inference: parameters replicated
  on it, batches of independent rollouts split over it."""
  devices = jax.local_devices()
  return jax.make_mesh((len(devices),), ("data",), axis_types=(AxisType.Auto,), devices=devices)


def shard_rollout_batch(*arrays):
  """Put arrays with a leading batch axis on :func:`local_data_mesh`, split over the devices,
  when the batch divides evenly between them; otherwise return them as they are (a replicated
  batch would make every device compute all of it). In a job of several processes they are
  returned as they are too: its parameters live on the job's mesh (a training run's evaluation),
  which every process feeds the same batch."""
  mesh = local_data_mesh()
  if (mesh.size == 1 or jax.process_count() > 1
      or any(np.shape(x)[0] % mesh.size for x in arrays)):
    return list(arrays)
  sharding = NamedSharding(mesh, PartitionSpec("data"))
  return [jax.device_put(x, sharding) for x in arrays]


def mesh_context(*arrays):
  """``jax.set_mesh`` of the first array laid out by a ``NamedSharding`` over several devices, or
  a null context. Kernels that XLA cannot partition (splash attention) read the mesh from it."""
  for x in arrays:
    sharding = getattr(x, "sharding", None)
    if isinstance(sharding, NamedSharding) and sharding.mesh.size > 1:
      return jax.set_mesh(sharding.mesh)
  return contextlib.nullcontext()


def abstract_with_shardings(abstract: Any, shardings: Any) -> Any:
  """ShapeDtypeStructs carrying the shardings to restore into."""
  return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract,
                      shardings)


def replicated_like(reference: Any) -> jax.sharding.Sharding | None:
  """Where an array replicated beside ``reference``'s first array lives: over that array's mesh
  when a ``NamedSharding`` lays it out, else on its device; None for host arrays."""
  placed = getattr(jax.tree.leaves(reference)[0], "sharding", None)
  if isinstance(placed, NamedSharding):
    return NamedSharding(placed.mesh, PartitionSpec())
  return placed


def replicated_beside(tree: Any, reference: Any) -> Any:
  """``tree``'s arrays put at :func:`replicated_like` ``(reference)`` (host arrays: unchanged),
  so that a jitted function takes both (e.g. a policy's parameters beside a world model's)."""
  placed = replicated_like(reference)
  return tree if placed is None else jax.device_put(tree, placed)
