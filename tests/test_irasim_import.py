"""wmjax.checkpoints.irasim: IRASim's state-dict keys <-> STDiT parameters, and `wmjax import
irasim` writing a workdir. The IRASim checkpoints here are synthetic: a tiny model's parameters
written under IRASim's key names and shapes by the mapping's inverse (no IRASim code)."""

import argparse
import json
import os
import sys

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wmjax.checkpoints import irasim

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FRAME_SHAPE = (8, 12, 4)

# configs/irasim.py shrunk to one tiny size, "T": what import_checkpoint reads as its config
TINY_CONFIG = f"""
from wmjax.config import load_config

SIZES = {{"T": (4, 32, 2)}}


def get_config(arg):
  size, dataset, variant = arg.split(",")
  config = load_config({os.path.join(ROOT, "configs", "irasim.py")!r} + f":S,{{dataset}},{{variant}}")
  config.model.depth, config.model.hidden_size, config.model.num_heads = SIZES[size]
  config.model.num_frames = config.data.frames = 4
  config.rollout.horizon = 3
  config.frame_shape = {FRAME_SHAPE!r}
  config.codec.kind = "pixel"  # no SDXL VAE here
  return config
"""


@pytest.fixture(scope="module")
def tiny_config(tmp_path_factory):
  path = tmp_path_factory.mktemp("configs") / "tiny_irasim.py"
  path.write_text(TINY_CONFIG)
  return str(path)


def random_params(network, seed):
  """Parameters of ``network`` with every leaf drawn from N(0, 1) (adaLN and output layers are
  zero at init and would hide a wrong mapping)."""
  n = network.num_frames
  params = nn.unbox(network.init(jax.random.key(0), jnp.zeros((1, n) + FRAME_SHAPE),
                                 jnp.zeros((1, n)), jnp.zeros((1, n - 1, network.action_dim))))
  leaves, tree = jax.tree.flatten(params)
  keys = jax.random.split(jax.random.key(seed), len(leaves))
  return jax.tree.unflatten(tree, [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])


def network_of(tiny_config, variant):
  from wmjax.model import WorldModel
  return WorldModel.from_config(irasim.import_config("T", "rt1", variant, tiny_config)).network


def outputs(network, params):
  n = network.num_frames
  x = jax.random.normal(jax.random.key(1), (2, n) + FRAME_SHAPE)
  actions = jax.random.normal(jax.random.key(2), (2, n - 1, network.action_dim))
  return np.asarray(network.apply(params, x, jnp.full((2, n), 321.0), actions))


def assert_same_params(a, b):
  assert jax.tree.structure(a) == jax.tree.structure(b)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.unit
@pytest.mark.parametrize("variant", ["frame_ada", "video_ada"])
@pytest.mark.slow
def test_round_trip_gives_the_same_parameters_and_outputs(tiny_config, variant):
  network = network_of(tiny_config, variant)
  params = random_params(network, seed=3)
  state = irasim.to_irasim(params, network, FRAME_SHAPE)
  # IRASim's names and shapes (one fused qkv per block, Conv2d patches, [1, D] mask embedding)
  d = network.hidden_size
  assert state["blocks.3.attn.qkv.weight"].shape == (3 * d, d)
  assert state["x_embedder.proj.weight"].shape == (d, 4, 2, 2)
  assert state["mask_emb_fn.weight"].shape == (1, d)
  assert state["embed_state.fc1.weight"].shape[1] == (7 if variant == "frame_ada" else 3 * 7)
  assert len([k for k in state if k.startswith("blocks.")]) == network.depth * 10
  back = irasim.from_irasim(state, network, FRAME_SHAPE)
  assert_same_params(back, params)
  np.testing.assert_array_equal(outputs(network, back), outputs(network, params))


@pytest.mark.unit
@pytest.mark.slow
def test_query_key_value_split_follows_irasims_head_layout(tiny_config):
  """IRASim reshapes qkv(x) to [B, N, 3, heads, d]: rows [k*D + h*d, k*D + (h+1)*d) of the fused
  weight are head h of q (k=0), k (k=1) or v (k=2)."""
  network = network_of(tiny_config, "frame_ada")
  state = irasim.to_irasim(random_params(network, seed=4), network, FRAME_SHAPE)
  params = irasim.from_irasim(state, network, FRAME_SHAPE)["params"]
  attn = params["blocks"]["layers"]["temporal"]["attn"]
  d, heads = network.hidden_size, network.num_heads
  w = state["blocks.3.attn.qkv.weight"]  # block 3: the temporal block of layer 1
  head = d // heads
  np.testing.assert_array_equal(attn["value"]["kernel"][1][:, 1], w[2 * d + head:2 * d + 2 * head].T)


def torch_checkpoint(path, states):
  """``states`` saved by torch as IRASim's main.py saves them: beside an optimiser state and its
  config object (an OmegaConf DictConfig there, a Namespace here; torch.load(weights_only=True)
  refuses both)."""
  torch = pytest.importorskip("torch")
  torch.save({name: {k: torch.from_numpy(np.array(v)) for k, v in state.items()}
              for name, state in states.items()}
             | {"opt": {"state": {}, "param_groups": []},
                "args": argparse.Namespace(dataset="rt1", learning_rate=1e-4)}, path)


@pytest.mark.integration
@pytest.mark.parametrize("weights", ["ema", "model"])
def test_import_writes_a_workdir_load_model_reads(tiny_config, tmp_path, weights):
  from wmjax.model import load_model
  network = network_of(tiny_config, "video_ada")
  params = {"ema": random_params(network, seed=5), "model": random_params(network, seed=6)}
  path = tmp_path / "rt1" / "checkpoints" / "video_ada" / "0300000.pt"
  path.parent.mkdir(parents=True)
  torch_checkpoint(path, {k: irasim.to_irasim(p, network, FRAME_SHAPE) for k, p in params.items()})

  irasim.import_checkpoint(str(path), str(tmp_path / "w"), weights=weights,
                           config_path=tiny_config)
  model = load_model(str(tmp_path / "w"))
  assert model.step == 300_000
  assert model.config.model.cond == "video" and model.config.sampling.context_shares_level
  assert model.action_stats.gripper_dim == 6
  np.testing.assert_allclose(model.action_stats.normalize(np.full((1, 7), 0.05))[0],
                             [1.0] * 6 + [0.05])  # IRASim's x20 arm scale, gripper as it is
  assert_same_params(model.params, params[weights])
  assert sorted(os.listdir(tmp_path)) == ["rt1", "w"]


@pytest.mark.integration
def test_cli_import(tiny_config, tmp_path, capsys):
  from wmjax.cli import main
  network = network_of(tiny_config, "frame_ada")
  path = tmp_path / "ckpt.pt"
  torch_checkpoint(path, {"ema": irasim.to_irasim(random_params(network, 7), network, FRAME_SHAPE)})
  assert main(["import", "irasim", str(path), "--workdir", str(tmp_path / "w"), "--dataset",
               "bridge", "--config", tiny_config]) == 0
  assert {"config.json", "checkpoints", "irasim_import.json"} <= set(os.listdir(tmp_path / "w"))
  assert "one trained with IRASim's final_frame_ada=True needs --final_frame_ada" in (
      capsys.readouterr().out)
  assert main(["import", "irasim", str(path), "--workdir", str(tmp_path / "ada"), "--dataset",
               "bridge", "--config", tiny_config, "--final_frame_ada"]) == 0
  saved = json.loads((tmp_path / "ada" / "config.json").read_text())
  assert saved["model"]["final_layer_actions"] is True
  assert json.loads((tmp_path / "w" / "config.json").read_text())[
      "model"]["final_layer_actions"] is False
  # Language-Table by either of IRASim's names: refused in one line, with the reason
  assert main(["import", "irasim", str(path), "--workdir", str(tmp_path / "lt"), "--dataset",
               "languagetable", "--config", tiny_config]) == 2
  assert "language_table models cannot be imported" in capsys.readouterr().err
  assert not (tmp_path / "lt").exists()


def broken(state, key_to_drop, key_to_add, key_to_reshape):
  state = dict(state)
  del state[key_to_drop]
  state[key_to_add] = np.zeros(3, np.float32)
  state[key_to_reshape] = np.zeros((5, 5), np.float32)
  return state


@pytest.mark.unit
def test_mismatches_are_listed_in_one_error(tiny_config):
  network = network_of(tiny_config, "frame_ada")
  state = irasim.to_irasim(random_params(network, 8), network, FRAME_SHAPE)
  with pytest.raises(irasim.IRASimImportError) as error:
    irasim.from_irasim(broken(state, "blocks.2.attn.qkv.bias", "lora.weight",
                              "final_layer.linear.weight"), network, FRAME_SHAPE)
  message = str(error.value)
  assert "1 missing: blocks.2.attn.qkv.bias" in message
  assert "1 unknown: lora.weight" in message
  assert "final_layer.linear.weight (5, 5) (expected (16, 32))" in message


@pytest.mark.unit
def test_fixed_embeddings_of_another_layout_are_refused(tiny_config):
  """The row-first 2-D sin-cos of wmjax's default is not IRASim's column-first one."""
  network = network_of(tiny_config, "frame_ada")
  state = irasim.to_irasim(random_params(network, 9), network, FRAME_SHAPE)
  state["pos_embed"] = irasim.layers.sincos_2d(32, 4, 6)[None]
  with pytest.raises(irasim.IRASimImportError, match="pos_embed"):
    irasim.from_irasim(state, network, FRAME_SHAPE)


@pytest.mark.integration
def test_a_bad_checkpoint_writes_nothing(tiny_config, tmp_path):
  network = network_of(tiny_config, "frame_ada")
  state = irasim.to_irasim(random_params(network, 10), network, FRAME_SHAPE)
  path = tmp_path / "ckpt.pt"
  torch_checkpoint(path, {"ema": broken(state, "t_embedder.mlp.0.bias", "extra", "blocks.0.mlp.fc1.weight"),
                          "model": state})
  with pytest.raises(irasim.IRASimImportError, match="1 missing: t_embedder.mlp.0.bias"):
    irasim.import_checkpoint(str(path), str(tmp_path / "w"), dataset="rt1",
                             config_path=tiny_config)
  assert os.listdir(tmp_path) == ["ckpt.pt"]


@pytest.mark.unit
def test_another_architecture_is_refused(tiny_config):
  with pytest.raises(irasim.IRASimImportError, match="not the state dict of an IRASim model"):
    irasim.infer_architecture({"conv_in.weight": np.zeros((1,))}, {"T": (4, 32, 2)}, 7)
  with pytest.raises(irasim.IRASimImportError, match="Language-Table"):
    irasim.infer_architecture({"embed_arm_state.weight": np.zeros((1,))}, {"T": (4, 32, 2)}, 7)


@pytest.mark.unit
def test_the_checkpoint_is_read_without_torch(monkeypatch, tmp_path):
  """Either state dict, as float32 arrays, with PyTorch not importable; a file that holds no
  such state dict says what it holds."""
  states = {"ema": {"a.weight": np.arange(6, dtype=np.float32).reshape(2, 3)},
            "model": {"a.weight": np.ones((2, 3), np.float32)}}
  torch_checkpoint(tmp_path / "ckpt.pt", states)
  torch_checkpoint(tmp_path / "ema_only.pt", {"ema": states["ema"]})
  torch = sys.modules["torch"]
  torch.save({"ema": {"a.weight": [1.0, 2.0]}}, tmp_path / "lists.pt")
  monkeypatch.setitem(sys.modules, "torch", None)
  for weights, state in states.items():
    read = irasim.read_state_dict(str(tmp_path / "ckpt.pt"), weights)
    assert read.keys() == state.keys() and read["a.weight"].dtype == np.float32
    np.testing.assert_array_equal(read["a.weight"], state["a.weight"])
  with pytest.raises(irasim.IRASimImportError,
                     match=r"ema_only.pt: it holds no 'model' state dict; it holds \['args', "
                           r"'ema', 'opt'\]"):
    irasim.read_state_dict(str(tmp_path / "ema_only.pt"), "model")
  with pytest.raises(irasim.IRASimImportError, match=r"lists.pt: it is not a state dict of "
                                                     r"tensors: \['a.weight'\]"):
    irasim.read_state_dict(str(tmp_path / "lists.pt"))
  (tmp_path / "notes.pt").write_text("not a checkpoint")
  with pytest.raises(irasim.IRASimImportError, match=r"notes.pt: not a PyTorch file"):
    irasim.read_state_dict(str(tmp_path / "notes.pt"))
