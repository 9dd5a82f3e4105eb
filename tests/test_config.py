"""Config schemas (wmjax.config): unknown keys and wrong types fail at load time naming the
nearest valid keys, defaults live in the schema, old saved configs load, one override syntax."""

import argparse
import glob
import json
import os
import pathlib

import pytest

from wmjax import config as config_lib
from wmjax.codecs import make_codec
from wmjax.config import ConfigError, apply_overrides, complete_config, load_config
from wmjax.tasks.gridworld import dataset as gridworld_data

ROOT = pathlib.Path(__file__).resolve().parents[1]
GRIDWORLD = str(ROOT / "configs" / "gridworld.py")


@pytest.mark.unit
def test_a_misspelt_override_names_the_key_meant():
  with pytest.raises(ConfigError, match=r"unknown config key 'train.num_stepz'; did you mean "
                                        r"train.num_steps\?"):
    load_config(GRIDWORLD, ["train.num_stepz=3"])
  # the second case: a misspelt builder_dir no longer falls back to the default
  with pytest.raises(ConfigError, match=r"'data.bulder_dir'; did you mean data.builder_dir\?"):
    load_config(str(ROOT / "configs" / "rt1.py:S"), ["--config.data.bulder_dir=/data/rt1"])
  with pytest.raises(ConfigError, match=r"'data.gridworld.num_sqares'; did you mean "
                                        r"data.gridworld.num_squares\?"):
    load_config(GRIDWORLD, ["data.gridworld.num_sqares=3"])
  with pytest.raises(ConfigError, match=r"'optimizer'; did you mean optim\?"):
    load_config(GRIDWORLD, ["optimizer.learning_rate=3"])
  with pytest.raises(ConfigError, match=r"'xyz'; the config has batch_size, codec, data"):
    load_config(GRIDWORLD, ["xyz=3"])


@pytest.mark.integration
def test_the_cli_refuses_a_misspelt_override_before_any_work(tmp_path, capsys):
  from wmjax.cli import main
  assert main(["train", "--config", GRIDWORLD, "--workdir", str(tmp_path / "run"),
               "--config.train.num_stepz=3"]) == 2
  assert "did you mean train.num_steps?" in capsys.readouterr().err
  assert not os.path.exists(tmp_path / "run" / "checkpoints")
  # the task module a config names is imported before any work, a misspelt one named
  assert main(["train", "--config", GRIDWORLD, "--workdir", str(tmp_path / "run"),
               "--config.task=wmjax.tasks.gridwrold"]) == 2
  assert "did you mean wmjax.tasks.gridworld?" in capsys.readouterr().err
  assert not os.path.exists(tmp_path / "run")


@pytest.mark.unit
def test_wrong_types_fail_and_values_take_the_schema_type():
  with pytest.raises(ConfigError, match=r"'train.num_steps' must be int, got abc$"):
    load_config(GRIDWORLD, ["train.num_steps=abc"])
  with pytest.raises(ConfigError, match=r"'sampling.kv_cache' must be bool, got 1"):
    load_config(GRIDWORLD, ["sampling.kv_cache=1"])
  with pytest.raises(ConfigError, match=r"'frame_shape' must be a tuple \(int, int, int\)"):
    load_config(GRIDWORLD, ["frame_shape=(16,16)"])
  with pytest.raises(ConfigError, match=r"'codec.random_vae' must be one of '', 'sdxl', 'sd3', "
                                        r"got sdx$"):
    load_config(GRIDWORLD, ["codec.random_vae=sdx"])
  with pytest.raises(ConfigError, match=r"'task' must name a module, e.g. 'wmjax.tasks.gridworld', "
                                        r"got 'wmjax/tasks/gridworld.py'"):
    load_config(GRIDWORLD, ["task=wmjax/tasks/gridworld.py"])
  with pytest.raises(ConfigError, match=r"config.task 'wmjax.frames' is a module but registers "
                                        r"no task"):
    load_config(GRIDWORLD, ["task=wmjax.frames"])
  config = load_config(GRIDWORLD, ["optim.learning_rate=1", "train.memory_budget_gib=3",
                                   "name=123", "mesh=[1,-1,1]", "model.dtype=bfloat16",
                                   "model.attention_impl=None", "data.builder_dir=/x",
                                   "codec.random_vae=sd3"])
  assert config.optim.learning_rate == 1.0 and isinstance(config.optim.learning_rate, float)
  assert config.train.memory_budget_gib == 3.0
  assert config.name == "123"  # a str key keeps the text
  assert config.mesh == (1, -1, 1) and config.model.dtype == "bfloat16"
  assert config.model.attention_impl is None and config.data.builder_dir == "/x"
  assert config.codec.random_vae == "sd3"  # one of a Literal's choices, bare or quoted


@pytest.mark.unit
def test_a_config_file_is_checked_when_it_loads(tmp_path):
  path = tmp_path / "typo.py"
  path.write_text(
      "from wmjax.config import load_config\n"
      f"def get_config():\n"
      f"  config = load_config({GRIDWORLD!r})\n"
      f"  config.train.unlock()\n"
      f"  config.train.num_stepz = 3\n"
      f"  return config\n")
  with pytest.raises(ConfigError, match=r"typo.py: unknown config key 'train.num_stepz'"):
    load_config(str(path))


@pytest.mark.unit
@pytest.mark.parametrize("path", sorted(glob.glob(str(ROOT / "configs" / "*.py"))),
                         ids=os.path.basename)
def test_every_config_file_loads_complete_and_round_trips(path):
  config = load_config(path)
  for section in ("codec", "data", "model", "diffusion", "sampling", "rollout", "optim",
                  "train"):
    assert section in config
  assert config.data.train_split and config.data.eval_split
  saved = json.loads(config.to_json())  # what a workdir stores
  assert json.loads(complete_config(saved).to_json()) == saved


LATENT_RECIPES = ("rt1.py", "bridge.py", "language_table.py", "wpe.py")


@pytest.mark.unit
@pytest.mark.parametrize("recipe", LATENT_RECIPES)
def test_each_latent_recipe_has_a_tiny_profile_without_weights(recipe):
  """`configs/<recipe>:tiny`: a random VAE (no folder) whose latents of the profile's frames are
  its frame_shape, windows and rollouts that fit its tiny model, and the recipe's own data,
  objective and optimiser (tests/test_recipes.py trains them)."""
  full = load_config(str(ROOT / "configs" / recipe))
  tiny = load_config(str(ROOT / "configs" / recipe) + ":tiny")
  assert tiny.codec.kind == "vae" and tiny.codec.random_vae and not tiny.codec.path
  codec = make_codec(tiny.codec)
  assert codec.latent_shape(tuple(tiny.data.resolution) + (3,)) == tuple(tiny.frame_shape)
  assert tiny.frame_shape[-1] == full.frame_shape[-1] == tiny.model.in_channels
  assert tiny.data.frames <= tiny.model.num_frames
  assert tiny.rollout.context + tiny.rollout.horizon <= tiny.model.num_frames
  assert tiny.model.hidden_size < full.model.hidden_size and tiny.batch_size < full.batch_size
  for section in ("diffusion", "optim"):
    assert tiny[section].to_dict() == full[section].to_dict(), section
  for key in ("dataset", "builder_dir", "train_split", "eval_split", "mixture", "spec"):
    assert tiny.data[key] == full.data[key], key


@pytest.mark.unit
def test_the_tiny_profile_names_what_it_shrinks():
  with pytest.raises(ValueError, match="name its dataset, e.g. 'tiny,rt1'"):
    load_config(str(ROOT / "configs" / "irasim.py:tiny"))
  with pytest.raises(ValueError, match=r"profile must be one of \('', 'tiny'\), got 'small'"):
    load_config(str(ROOT / "configs" / "wpe.py:small"))


@pytest.mark.unit
def test_a_config_saved_by_an_older_version_loads_with_defaults():
  saved = json.loads(load_config(GRIDWORLD).to_json())
  for section, key in (("data", "train_split"), ("data", "eval_split"), ("sampling", "kv_cache"),
                       ("optim", "grad_accum"), ("train", "auto_fit"), ("model", "remat")):
    del saved[section][key]
  del saved["data"]["gridworld"]["snap_to_pixels"]
  del saved["rollout"], saved["codec"], saved["task"]
  saved["model"]["since_removed"] = 1
  with pytest.raises(ConfigError, match="since_removed"):
    complete_config(saved)
  with pytest.raises(ConfigError, match="model.mlp_kernel no longer exists: the fused"):
    complete_config({**saved, "model": {"mlp_kernel": "xla"}})
  saved["model"]["mlp_kernel"] = "pallas"  # retired: a saved config drops it
  config = complete_config(saved, strict=False)
  assert config.data.train_split == "train" and config.data.eval_split == "test"
  assert config.sampling.kv_cache is False and config.optim.grad_accum == 1
  assert config.train.auto_fit is True and config.model.remat == "none"
  assert config.rollout.to_dict() == {"context": 1, "horizon": 15, "short_actions": None}
  assert config.codec.kind == "pixel"
  # the gridworld's own convention: positions before snap_to_pixels existed were sub-pixel
  assert config.data.gridworld.snap_to_pixels is False
  assert config.model.since_removed == 1 and "mlp_kernel" not in config.model
  # the task of a config saved before config.task existed: the one generating its dataset
  assert config.task == "wmjax.tasks.gridworld"
  # a new config that leaves the key (or the whole section) out gets the documented default
  fresh = json.loads(load_config(GRIDWORLD).to_json())
  del fresh["data"]["gridworld"]["snap_to_pixels"]
  assert complete_config(fresh).data.gridworld.snap_to_pixels is True
  del fresh["data"]["gridworld"]
  assert gridworld_data.GridworldConfig.from_dict(
      complete_config(fresh).data.get("gridworld", {})).snap_to_pixels is True
  # and overrides apply to it like to a config file
  assert apply_overrides(saved, ["sampling.num_steps=4"], strict=False).sampling.num_steps == 4


@pytest.mark.unit
def test_section_helpers_check_fields():
  assert config_lib.optim_config().grad_clip == config_lib.OptimConfig().grad_clip
  with pytest.raises(ConfigError, match=r"'model.hiden_size'; did you mean model.hidden_size"):
    config_lib.model_config(hiden_size=3)
  mixture = load_config(str(ROOT / "configs" / "wpe.py")).data.mixture
  assert mixture.bridge.train_split == "train" and mixture.bridge.frame_step is None


@pytest.mark.unit
def test_one_override_syntax_for_scripts():
  parser = argparse.ArgumentParser()
  parser.add_argument("--config")
  parser.add_argument("--batch", type=int)
  args, overrides = config_lib.parse_args_with_overrides(
      parser, ["--config", GRIDWORLD, "--config.train.num_steps=3", "--batch", "2",
               "--config.mesh=(1,-1,1)"])
  assert args.config == GRIDWORLD and args.batch == 2
  assert overrides == ["--config.train.num_steps=3", "--config.mesh=(1,-1,1)"]
  assert load_config(args.config, overrides).mesh == (1, -1, 1)
  with pytest.raises(ConfigError, match="has no value"):
    config_lib.split_overrides(["--config.train.num_steps"])
  with pytest.raises(SystemExit):  # the old --set is gone
    config_lib.parse_args_with_overrides(parser, ["--set", "train.num_steps=3"])
