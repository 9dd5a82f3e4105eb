"""IRASim's published checkpoints as wmjax workdirs.

IRASim (bytedance/IRASim, ``models/irasim.py``, class ``IRASim``) saves PyTorch ``.pt`` files
holding ``{"model", "ema", "opt"}`` state dicts and its config as ``"args"`` (or one bare state
dict); :func:`read_state_dict` reads one of them without PyTorch
(:mod:`wmjax.checkpoints.torch_file`). :func:`from_irasim`
maps such a state dict onto the parameters of the matching :class:`wmjax.nn.STDiT`,
:func:`to_irasim` is its inverse, and :func:`import_checkpoint` writes a workdir (``config.json``
and an orbax checkpoint in ``checkpoints/``) that :func:`wmjax.model.load_model`, ``wmjax
evaluate`` and ``wmjax rollout`` read like a training workdir.

The config is ``configs/irasim.py:SIZE,DATASET,VARIANT`` with what IRASim's code does where wmjax
defaults differ (:data:`CODE_OPTIONS`): the 2-D sin-cos positions put the column first, the
temporal sin-cos embedding joins before the first temporal block, Frame-Ada's final layer sees
the timestep only (the published checkpoints were trained with ``final_frame_ada=False``), and
sampling shows the clean context frame at the new frames' timestep, with IRASim's evaluation
sampler (PNDM with its Runge-Kutta warm-up, 50 steps). The action statistics are
IRASim's fixed scaling (``c_act_scaler``: x20 for the arm, x1 for the gripper) written as a
mean 0 / std ``1/scale`` normalisation; they were not measured (``count`` 0), and ``min`` /
``max`` / ``p01`` / ``p99`` are the raw range ``[-1/scale, 1/scale]`` that the scaling maps to
``[-1, 1]``. IRASim's actions are end-effector moves in the previous end-effector frame and the
absolute gripper state (``dataset/dataset_3D.py``), which the user's actions must follow.

Language-Table checkpoints are refused: IRASim embeds its 2-D actions with two linear maps and no
activation (Frame-Ada), or per step and then by an MLP over the concatenated step embeddings
(Video-Ada), neither of which :class:`wmjax.nn.layers.ActionEmbedder` computes.

Parameter layout (IRASim ``key`` -> wmjax path; ``L`` = layer ``i // 2``, even blocks spatial,
odd blocks temporal; a torch ``Linear`` weight ``[out, in]`` is the transposed Flax kernel)::

  x_embedder.proj (Conv2d [D, C, p, p])  patch_embed/proj (kernel [(py px c), D])
  t_embedder.mlp.0 / .2                  time_embed/fc1 / fc2
  embed_state.fc1 / .fc2                 action_embed/mlp (Frame-Ada) or trajectory_embed/mlp
  mask_emb_fn.weight [1, D]              null_action [D]
  blocks.i.attn.qkv [3D, D]              blocks/layers/{spatial|temporal}/attn/query, key, value
  blocks.i.attn.proj                     .../attn/out (kernel [H, d, D])
  blocks.i.mlp.fc1 / fc2                 .../mlp/fc1 / fc2
  blocks.i.adaLN_modulation.1            .../modulation/proj
  final_layer.adaLN_modulation.1         final_layer/modulation/proj
  final_layer.linear                     final_layer/linear
  pos_embed, temp_embed (fixed sin-cos)  checked against the config's, not stored
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import tempfile
from typing import Any, Callable, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax.checkpoints import torch_file
from wmjax.config import load_config, shipped_config
from wmjax.data import irasim as data_irasim
from wmjax.data.stats import ActionStats
from wmjax.model import WorldModel
from wmjax.nn import layers

# What IRASim's code does where wmjax's defaults differ (see the module docstring).
CODE_OPTIONS = ("model.spatial_sincos_columns_first=True",
                "model.temporal_sincos_at='first_temporal'",
                "sampling.context_level=-1", "sampling.context_shares_level=True",
                "sampling.sampler='pndm_prk'")  # 50 steps, 59 calls: IRASim's evaluation
# IRASim's dataset names -> configs/irasim.py's; the action scale of each (c_act_scaler) and its
# gripper dimension.
DATASETS = {"rt1": "rt1", "bridge": "bridge", "languagetable": "language_table",
            "language_table": "language_table"}
ACTION_SCALES = {"rt1": (data_irasim.action_scale("3d"), 6),
                 "bridge": (data_irasim.action_scale("3d"), 6)}
WEIGHTS = ("ema", "model")
DEFAULT_CONFIG = shipped_config("irasim.py")
MAX_LISTED = 5  # mismatches named in an error


class IRASimImportError(ValueError):
  """A file that is not a checkpoint of an IRASim model wmjax can hold, with the reasons."""


# --------------------------------------------------------------------------- parameter mapping


@dataclasses.dataclass(frozen=True)
class Rule:
  """Some IRASim tensors <-> some wmjax parameters, with the conversion both ways.

  ``wmjax`` paths are '/'-joined under ``params``; with ``layer`` they name a slice of the
  stacked (scanned) layers."""

  irasim: tuple[str, ...]
  wmjax: tuple[str, ...]
  to_wmjax: Callable[..., tuple]
  to_irasim: Callable[..., tuple]
  layer: int | None = None


def _linear(irasim: str, wmjax: str, layer: int | None = None) -> Rule:
  """torch ``Linear`` (weight ``[out, in]``, bias) <-> Flax ``Dense`` (kernel ``[in, out]``)."""
  swap = lambda a, b: (a.T, b)
  return Rule((f"{irasim}.weight", f"{irasim}.bias"), (f"{wmjax}/kernel", f"{wmjax}/bias"),
              swap, swap, layer)


def _qkv(irasim: str, wmjax: str, heads: int, layer: int) -> Rule:
  """One ``Linear(D, 3D)`` (q, k, v stacked, heads inside each) <-> three ``[D, H, d]`` kernels
  and ``[H, d]`` biases."""

  def to_wmjax(w, b):
    d = w.shape[1]
    w = w.reshape(3, heads, d // heads, d).transpose(0, 3, 1, 2)  # [3, D, H, d]
    b = b.reshape(3, heads, d // heads)
    return (w[0], w[1], w[2], b[0], b[1], b[2])

  def to_irasim(kq, kk, kv, bq, bk, bv):
    d = kq.shape[0]
    w = jnp.stack([kq, kk, kv]).transpose(0, 2, 3, 1).reshape(3 * d, d)
    return (w, jnp.stack([bq, bk, bv]).reshape(3 * d))

  names = ("query", "key", "value")
  return Rule((f"{irasim}.weight", f"{irasim}.bias"),
              tuple(f"{wmjax}/{n}/kernel" for n in names) + tuple(f"{wmjax}/{n}/bias" for n in names),
              to_wmjax, to_irasim, layer)


def _attn_out(irasim: str, wmjax: str, heads: int, layer: int) -> Rule:
  """``Linear(D, D)`` on the concatenated heads <-> the ``[H, d, D]`` output kernel."""
  return Rule((f"{irasim}.weight", f"{irasim}.bias"), (f"{wmjax}/kernel", f"{wmjax}/bias"),
              lambda w, b: (w.T.reshape(heads, -1, w.shape[0]), b),
              lambda k, b: (k.reshape(-1, k.shape[-1]).T, b), layer)


def _patch_embed(patch: int) -> Rule:
  """``Conv2d`` weight ``[D, C, p, p]`` <-> kernel ``[p*p*C, D]`` over (py, px, c) pixels."""
  return Rule(("x_embedder.proj.weight", "x_embedder.proj.bias"),
              ("patch_embed/proj/kernel", "patch_embed/proj/bias"),
              lambda w, b: (w.transpose(2, 3, 1, 0).reshape(-1, w.shape[0]), b),
              lambda k, b: (k.reshape(patch, patch, -1, k.shape[1]).transpose(3, 2, 0, 1), b))


def rules(network) -> list[Rule]:
  """The mapping of an IRASim-shaped :class:`wmjax.nn.STDiT` (cond 'frame' or 'video')."""
  if network.cond not in ("frame", "video") or network.action_encoding != "raw":
    raise IRASimImportError(f"IRASim models condition on raw actions per frame (Frame-Ada) or "
                            f"per window (Video-Ada), not cond={network.cond!r}")
  action = "action_embed" if network.cond == "frame" else "trajectory_embed"
  out = [_patch_embed(network.patch_size),
         _linear("t_embedder.mlp.0", "time_embed/fc1"),
         _linear("t_embedder.mlp.2", "time_embed/fc2"),
         _linear("embed_state.fc1", f"{action}/mlp/fc1"),
         _linear("embed_state.fc2", f"{action}/mlp/fc2"),
         Rule(("mask_emb_fn.weight",), ("null_action",), lambda w: (w[0],), lambda v: (v[None],)),
         _linear("final_layer.adaLN_modulation.1", "final_layer/modulation/proj"),
         _linear("final_layer.linear", "final_layer/linear")]
  for i in range(network.depth):
    layer, kind = i // 2, ("spatial", "temporal")[i % 2]
    wm, ir = f"blocks/layers/{kind}", f"blocks.{i}"
    out += [_qkv(f"{ir}.attn.qkv", f"{wm}/attn", network.num_heads, layer),
            _attn_out(f"{ir}.attn.proj", f"{wm}/attn/out", network.num_heads, layer),
            _linear(f"{ir}.mlp.fc1", f"{wm}/mlp/fc1", layer),
            _linear(f"{ir}.mlp.fc2", f"{wm}/mlp/fc2", layer),
            _linear(f"{ir}.adaLN_modulation.1", f"{wm}/modulation/proj", layer)]
  return out


def fixed_embeddings(network, frame_shape: tuple[int, int, int]) -> dict[str, np.ndarray]:
  """IRASim's buffers ``pos_embed [1, P, D]`` and ``temp_embed [1, F, D]`` as the network
  computes them (``spatial_sincos_columns_first`` decides the order of ``pos_embed``)."""
  p, d = network.patch_size, network.hidden_size
  grid = layers.sincos_2d(d, frame_shape[0] // p, frame_shape[1] // p,
                          network.spatial_sincos_columns_first)
  return {"pos_embed": grid[None],
          "temp_embed": layers.sincos_1d(d, np.arange(network.num_frames))[None]}


def _flat(params: Mapping) -> dict[str, Any]:
  return {"/".join(str(k.key) for k in path): leaf
          for path, leaf in jax.tree_util.tree_leaves_with_path(params["params"])}


def _unflat(flat: Mapping[str, Any]) -> dict:
  tree: dict = {}
  for path, leaf in flat.items():
    *parents, name = path.split("/")
    node = tree
    for part in parents:
      node = node.setdefault(part, {})
    node[name] = leaf
  return {"params": tree}


def _irasim_tensors(params: Mapping, network) -> dict[str, Any]:
  """The learned tensors of :func:`to_irasim` (traceable: ``jax.eval_shape`` gives shapes)."""
  flat = _flat(params)
  out = {}
  for rule in rules(network):
    leaves = [flat[k] if rule.layer is None else flat[k][rule.layer] for k in rule.wmjax]
    out.update(zip(rule.irasim, rule.to_irasim(*leaves)))
  return out


def to_irasim(params: Mapping, network, frame_shape: tuple[int, int, int]
              ) -> dict[str, np.ndarray]:
  """wmjax parameters (``{'params': ...}``, scanned layers) -> IRASim's state dict (float32
  numpy arrays under IRASim's keys, its fixed sin-cos buffers included)."""
  out = {k: np.asarray(v, np.float32) for k, v in _irasim_tensors(params, network).items()}
  out.update(fixed_embeddings(network, frame_shape))
  return out


def expected_shapes(network, frame_shape: tuple[int, int, int]) -> dict[str, tuple[int, ...]]:
  """IRASim's ``key -> shape`` for ``network`` on frames of ``frame_shape``."""
  n = network.num_frames
  abstract = jax.eval_shape(network.init, jax.random.key(0),
                            jnp.zeros((1, n) + tuple(frame_shape)), jnp.zeros((1, n)),
                            jnp.zeros((1, n - 1, network.action_dim)))
  tensors = jax.eval_shape(lambda p: _irasim_tensors(p, network), nn.unbox(abstract))
  shapes = {k: tuple(v.shape) for k, v in tensors.items()}
  shapes.update({k: v.shape for k, v in fixed_embeddings(network, frame_shape).items()})
  return shapes


def check_state_dict(state: Mapping[str, Any], network, frame_shape: tuple[int, int, int]
                     ) -> None:
  """:class:`IRASimImportError` listing the first few missing, unknown and misshaped keys, and
  fixed sin-cos buffers that differ from the network's, if there are any."""
  expected = expected_shapes(network, frame_shape)
  missing = [k for k in expected if k not in state]
  unknown = [k for k in state if k not in expected]
  misshaped = [f"{k} {tuple(state[k].shape)} (expected {expected[k]})" for k in expected
               if k in state and tuple(state[k].shape) != expected[k]]
  problems = [(f"{len(missing)} missing", missing), (f"{len(unknown)} unknown", unknown),
              (f"{len(misshaped)} of another shape", misshaped)]
  if not (missing or unknown or misshaped):
    for key, value in fixed_embeddings(network, frame_shape).items():
      if not np.allclose(np.asarray(state[key], np.float32), value, atol=1e-5):
        problems.append(("1 fixed embedding differs from the sin-cos of the config",
                         [f"{key} (another frame size or position layout)"]))
  reasons = [f"{what}: {', '.join(keys[:MAX_LISTED])}{', ...' if len(keys) > MAX_LISTED else ''}"
             for what, keys in problems if keys]
  if reasons:
    raise IRASimImportError("the state dict does not fit " + describe(network, frame_shape)
                            + ": " + "; ".join(reasons))


def describe(network, frame_shape) -> str:
  variant = "Frame-Ada" if network.cond == "frame" else "Video-Ada"
  return (f"IRASim {variant} with {network.depth} blocks of width {network.hidden_size}, "
          f"patch {network.patch_size}, {network.num_frames} frames of {tuple(frame_shape)}, "
          f"actions of {network.action_dim}")


def from_irasim(state: Mapping[str, Any], network, frame_shape: tuple[int, int, int]) -> dict:
  """IRASim's state dict (numpy arrays or anything ``np.asarray`` takes) -> wmjax parameters
  ``{'params': ...}`` (float32, scanned layers); :class:`IRASimImportError` when it does not
  fit ``network`` (:func:`check_state_dict`)."""
  check_state_dict(state, network, frame_shape)
  flat: dict[str, Any] = {}
  per_layer: dict[str, dict[int, Any]] = {}
  for rule in rules(network):
    values = rule.to_wmjax(*(np.asarray(state[k], np.float32) for k in rule.irasim))
    for path, value in zip(rule.wmjax, values):
      if rule.layer is None:
        flat[path] = value
      else:
        per_layer.setdefault(path, {})[rule.layer] = value
  for path, slices in per_layer.items():
    flat[path] = np.stack([slices[i] for i in range(len(slices))])
  return _unflat({k: np.ascontiguousarray(v, np.float32) for k, v in flat.items()})


# --------------------------------------------------------------------------- the file


def _state_dict(checkpoint: Any, weights: str) -> Mapping[str, Any]:
  """The ``weights`` state dict of a checkpoint's object (``{"model", "ema", ...}`` or one bare
  state dict), every value a tensor."""
  if not isinstance(checkpoint, Mapping):
    raise IRASimImportError(f"it holds a {type(checkpoint).__name__}, not a state dict")
  if "model" in checkpoint or "ema" in checkpoint:
    if weights not in checkpoint:
      raise IRASimImportError(f"it holds no {weights!r} state dict; it holds {sorted(checkpoint)}")
    checkpoint = checkpoint[weights]
  if not isinstance(checkpoint, Mapping) or not all(
      isinstance(v, torch_file.StoredTensor) for v in checkpoint.values()):
    keys = list(checkpoint)[:5] if isinstance(checkpoint, Mapping) else checkpoint
    raise IRASimImportError(f"it is not a state dict of tensors: {keys}")
  return checkpoint


def read_state_dict(path: str, weights: str = "ema") -> dict[str, np.ndarray]:
  """The ``weights`` ('ema' or 'model') state dict of an IRASim ``.pt`` file as float32 numpy
  arrays (a file holding one bare state dict gives that one), read without PyTorch
  (:mod:`wmjax.checkpoints.torch_file`: only that state dict's tensors are read, and nothing the
  file names runs, so the optimiser state and IRASim's pickled config cost nothing)."""
  if weights not in WEIGHTS:
    raise ValueError(f"weights must be one of {WEIGHTS}, got {weights!r}")
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no IRASim checkpoint at {path}")
  try:
    with torch_file.load(path) as checkpoint:
      state = _state_dict(checkpoint, weights)
      return {k: v.numpy().astype(np.float32) for k, v in state.items()}
  except (torch_file.TorchFileError, IRASimImportError) as e:
    raise IRASimImportError(f"{path}: {e}") from e


@dataclasses.dataclass(frozen=True)
class Architecture:
  """What a state dict says about the model: size name, variant, frames."""

  size: str
  variant: str
  num_frames: int


def infer_architecture(state: Mapping[str, Any], sizes: Mapping[str, tuple[int, int, int]],
                       action_dim: int, variant: str | None = None) -> Architecture:
  """Size (by blocks and width, ``sizes`` of configs/irasim.py), variant (by the action
  embedder's input: one action, Frame-Ada, or a window of them, Video-Ada) and window length."""
  if "embed_arm_state.weight" in state:
    raise IRASimImportError("a Language-Table checkpoint (embed_arm_state): IRASim embeds its "
                            "actions with linear maps wmjax's STDiT does not have (see "
                            "wmjax.checkpoints.irasim)")
  needed = ("x_embedder.proj.weight", "temp_embed", "embed_state.fc1.weight")
  absent = [k for k in needed if k not in state]
  if absent:
    raise IRASimImportError(f"not the state dict of an IRASim model: no {', '.join(absent)} "
                            f"(keys: {', '.join(list(state)[:MAX_LISTED])}, ...)")
  depth = len({int(m.group(1)) for k in state if (m := re.match(r"blocks\.(\d+)\.", k))})
  hidden = state["x_embedder.proj.weight"].shape[0]
  size = next((name for name, (d, h, _) in sizes.items() if (d, h) == (depth, hidden)), None)
  if size is None:
    raise IRASimImportError(f"{depth} blocks of width {hidden} are no IRASim size "
                            f"({', '.join(f'{n}: {d}x{h}' for n, (d, h, _) in sizes.items())})")
  num_frames = state["temp_embed"].shape[1]
  if variant is None:
    inputs = state["embed_state.fc1.weight"].shape[1]
    variant = {action_dim: "frame_ada", (num_frames - 1) * action_dim: "video_ada"}.get(inputs)
    if variant is None:
      raise IRASimImportError(f"the action embedder takes {inputs} numbers: neither one action "
                              f"({action_dim}, Frame-Ada) nor {num_frames - 1} (Video-Ada)")
  return Architecture(size, variant, num_frames)


def dataset_from_path(path: str) -> str | None:
  """The IRASim dataset a checkpoint's path names (its release layout is
  ``DATASET/checkpoints/VARIANT/STEP.pt``), or None."""
  parts = [p.lower() for p in os.path.normpath(os.path.abspath(path)).split(os.sep)]
  found = {DATASETS[p] for p in parts if p in DATASETS}
  return found.pop() if len(found) == 1 else None


def step_from_path(path: str) -> int:
  """The training step of IRASim's ``0300000.pt`` file names; 0 for other names."""
  digits = re.fullmatch(r"(\d+)\.pt", os.path.basename(path))
  return int(digits.group(1)) if digits else 0


def import_config(size: str, dataset: str, variant: str, config_path: str = DEFAULT_CONFIG,
                  final_frame_ada: bool = False) -> ml_collections.ConfigDict:
  """``configs/irasim.py:SIZE,DATASET,VARIANT`` with :data:`CODE_OPTIONS`; a Frame-Ada final
  layer sees the actions too only with ``final_frame_ada`` (IRASim's option of that name; its
  published checkpoints were trained without it, and the weights do not tell)."""
  options = CODE_OPTIONS + ((f"model.final_layer_actions={final_frame_ada}",)
                            if variant == "frame_ada" else ())
  return load_config(f"{config_path}:{size},{dataset},{variant}", options)


def action_stats(dataset: str) -> ActionStats:
  """IRASim's fixed action scaling of ``dataset`` as mean 0 / std ``1/scale`` statistics."""
  if dataset not in ACTION_SCALES:
    raise IRASimImportError(f"IRASim's {dataset} models cannot be imported (see "
                            f"wmjax.checkpoints.irasim); importable: {sorted(ACTION_SCALES)}")
  scales, gripper = ACTION_SCALES[dataset]
  std = 1.0 / np.asarray(scales)
  zero = np.zeros_like(std)
  return ActionStats(dataset=f"irasim-{dataset}", count=0, mean=zero, std=std, p01=-std,
                     p99=std, min=-std, max=std, gripper_dim=gripper)


def convert(path: str, *, dataset: str | None = None, variant: str | None = None,
            weights: str = "ema", config_path: str = DEFAULT_CONFIG,
            final_frame_ada: bool = False):
  """Read and convert an IRASim ``.pt`` file -> ``(config, params, stats, step)``; nothing is
  written. ``dataset`` (rt1, bridge) and ``variant`` (frame_ada, video_ada) default to what the
  path and the weights say; ``final_frame_ada`` as in :func:`import_config`."""
  if dataset is not None and dataset not in DATASETS:
    raise ValueError(f"dataset must be one of {', '.join(sorted(ACTION_SCALES))} (IRASim's "
                     f"names), got {dataset!r}")
  dataset = DATASETS[dataset] if dataset else dataset_from_path(path)
  if dataset is None:
    raise ValueError(f"cannot tell the dataset from {path}: name it (rt1 or bridge)")
  stats = action_stats(dataset)
  if variant is not None and variant not in ("frame_ada", "video_ada"):
    raise ValueError(f"variant must be 'frame_ada' or 'video_ada', got {variant!r}")
  state = read_state_dict(path, weights)
  sizes = _config_sizes(config_path)
  arch = infer_architecture(state, sizes, stats.action_dim, variant)
  config = import_config(arch.size, dataset, arch.variant, config_path, final_frame_ada)
  network = WorldModel.from_config(config).network
  if arch.num_frames != network.num_frames:
    raise IRASimImportError(f"the checkpoint's window is {arch.num_frames} frames, the "
                            f"config's {network.num_frames}")
  params = from_irasim(state, network, tuple(config.frame_shape))
  return config, params, stats, step_from_path(path)


def _config_sizes(config_path: str) -> dict[str, tuple[int, int, int]]:
  """``SIZES`` of configs/irasim.py: name -> (blocks, width, heads)."""
  import importlib.util
  if not os.path.isfile(config_path):
    raise FileNotFoundError(f"no IRASim config at {config_path}; name configs/irasim.py of a "
                            f"wmjax checkout")
  spec = importlib.util.spec_from_file_location("_irasim_config", config_path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.SIZES


# --------------------------------------------------------------------------- the workdir


def write_workdir(workdir: str, config: ml_collections.ConfigDict, params: dict,
                  stats: ActionStats, step: int, source: dict) -> str:
  """A workdir holding ``config.json``, ``irasim_import.json`` (``source``) and one orbax
  checkpoint at ``step`` whose ``ema_params`` are ``params``. Written beside ``workdir`` and
  renamed into place, so a failure leaves nothing; an existing non-empty ``workdir`` is refused."""
  from wmjax.train.checkpoint import Checkpointer

  workdir = os.path.abspath(os.path.expanduser(workdir))
  if os.path.exists(workdir) and (not os.path.isdir(workdir) or os.listdir(workdir)):
    raise FileExistsError(f"{workdir} exists and is not empty; import into a new directory")
  parent = os.path.dirname(workdir)
  os.makedirs(parent, exist_ok=True)
  staging = tempfile.mkdtemp(prefix=f".{os.path.basename(workdir)}.import-", dir=parent)
  try:
    checkpoints = Checkpointer(os.path.join(staging, "checkpoints"), max_to_keep=1)
    try:
      state = {"ema_params": jax.tree.map(jnp.asarray, params)}
      checkpoints.save(step, state, json.loads(config.to_json()), stats.to_dict())
      checkpoints.wait()
    finally:
      checkpoints.close()
    with open(os.path.join(staging, "config.json"), "w") as f:
      f.write(config.to_json(indent=2))
    with open(os.path.join(staging, "irasim_import.json"), "w") as f:
      json.dump(source, f, indent=2)
    if os.path.isdir(workdir):
      os.rmdir(workdir)  # empty
    os.rename(staging, workdir)
  except BaseException:
    shutil.rmtree(staging, ignore_errors=True)
    raise
  return workdir


def import_checkpoint(path: str, workdir: str, *, dataset: str | None = None,
                      variant: str | None = None, weights: str = "ema",
                      config_path: str = DEFAULT_CONFIG,
                      final_frame_ada: bool = False) -> ml_collections.ConfigDict:
  """Convert the IRASim checkpoint ``path`` into a new wmjax ``workdir``; its config."""
  config, params, stats, step = convert(path, dataset=dataset, variant=variant, weights=weights,
                                        config_path=config_path, final_frame_ada=final_frame_ada)
  source = dict(checkpoint=os.path.abspath(path), weights=weights, step=step, config=config.name)
  write_workdir(workdir, config, params, stats, step, source)
  return config
