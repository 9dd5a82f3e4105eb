"""The real-data recipes (configs/rt1.py, bridge.py, language_table.py, wpe.py) on the Open-X
fixture datasets, at their `:tiny` profile (a tiny model, a random tiny VAE, no weights):
bridge.py and wpe.py train one step and roll out; rt1.py and language_table.py, bridge.py's model
on other datasets, read their datasets for their models; pre-encoded latents (`wmjax data
encode`) train the same way."""

import glob
import importlib.util
import json
import os

import numpy as np
import pytest

import oxe_fixtures
from conftest import ROOT, one_line_error
from wmjax import cli
from wmjax.codecs import make_codec
from wmjax.config import load_config
from wmjax.data.latents import LatentEpisodes
from wmjax.data.rlds import make_window
from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.env import WorldModelEnv
from wmjax.eval.evaluate import evaluate_checkpoint
from wmjax.frames import to_model
from wmjax.model import load_model
from wmjax.train.data import build_data, eval_windows
from wmjax.train.loop import train

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.fixture(scope="module")
def builders(tmp_path_factory):
  root = tmp_path_factory.mktemp("recipes")
  return {name: oxe_fixtures.build(name, str(root / "data"), file_format="array_record")
          for name in ("fractal20220817_data", "bridge", "language_table")}


def _data(recipe, builders) -> dict:
  """Overrides that point ``recipe`` at the fixture datasets, whose one split is ``train``."""
  if recipe == "wpe.py":
    return {f"data.mixture.{name}.{key}": value for name, builder in builders.items()
            for key, value in (("builder_dir", builder), ("train_split", "train"),
                               ("eval_split", "train"))}
  dataset = load_config(str(ROOT / "configs" / recipe)).data.dataset
  return {"data.builder_dir": builders[dataset], "data.train_split": "train",
          "data.eval_split": "train"}


def _config(recipe, builders, **extra):
  """``configs/<recipe>:tiny`` on the fixture datasets, trained one step."""
  values = {**_data(recipe, builders), "train.num_steps": 1, **extra}
  return load_config(str(ROOT / "configs" / recipe) + ":tiny",
                     [f"{k}={v!r}" for k, v in values.items()])


# Every shipped config file and profile, and the test that trains it one step on tiny data of its
# kind (test_every_shipped_config_is_trained_by_a_test keeps this complete). rt1.py and
# language_table.py are bridge.py's model and codec (configs/irasim.py) on other datasets: bridge.py
# trains here, and their datasets are read for their models by test_recipe_reads_its_dataset.
RECIPES = ("bridge.py", "wpe.py")
READ_HERE = ("rt1.py", "language_table.py")
TRAINED_ELSEWHERE = {
    "irasim.py": "the model of rt1.py, bridge.py and language_table.py (its recipes)",
    "wpe_600m.py": "the model of wpe.py",
    "gridworld.py": "test_train_loop.py, test_overfit.py and the quickstart",
    "pusht.py:cpu": "test_pusht.py (the experiment fixture trains it)",
    "pusht.py:h100": "test_pusht.py::test_h100_profile_trains_one_step",
    "pusht.py:latent": "test_pusht.py::test_latent_profile_fits_a_codec_to_its_data_and_trains_on_"
                       "its_latents",
    "rlds.py": "test_data_specs.py::test_own_lerobot_data_from_import_to_evaluation (inspect's "
               "command)",
    "metaworld.py": "test_metaworld.py::test_the_profile_trains_and_evaluates_two_views",
}


@pytest.mark.parametrize("recipe", RECIPES)
def test_recipe_trains_one_step_and_rolls_out(recipe, builders, tmp_path):
  # wpe.py evaluates in the training loop; bridge.py through `evaluate_checkpoint` (below) only
  config = _config(recipe, builders, **({"train.eval_every": 0} if recipe == "bridge.py" else {}))
  _, result = train(config, str(tmp_path))
  assert result["step"] == 1
  if recipe == "wpe.py":
    assert np.isfinite(result["val_loss"]) and np.isfinite(result["rollout_psnr"])
    assert (tmp_path / "rollout.gif").exists()
  model = load_model(str(tmp_path))
  image_shape = tuple(config.data.resolution) + (3,)
  assert model.image_shape == image_shape and config.codec.random_vae
  if recipe == "wpe.py":  # every member's statistics travel with the checkpoint
    stats = json.loads((tmp_path / "checkpoints" / "1" / "action_stats" / "metadata").read_text())
    assert sorted(stats["mixture"]) == ["bridge", "fractal20220817_data", "language_table"]
  if recipe == "bridge.py":  # the evaluation protocols through the (random, tiny) VAE
    _, results = evaluate_checkpoint(str(tmp_path), split="train", protocols=("short", "long"),
                                     batch_size=2, videos=1)
    # fixture episodes of 5, 3 and 7 steps: 2 windows of 4 frames, 3 whole episodes
    assert (results["short"]["trajectories"], results["long"]["trajectories"]) == (2, 3)
    for protocol in ("short", "long"):
      for name in ("mse", "psnr", "ssim"):
        assert np.isfinite(results[protocol]["model"][name]["mean"]), (protocol, name)
      # a random VAE's latents have no scale: IRASim's latent L2 is left out, with the reason
      assert "latent_l2" not in results[protocol]["model"]
      assert "randomly initialised" in results[protocol]["left_out"][0]
    report = (tmp_path / "eval" / "train-step1" / "report.md").read_text()
    assert "latent_l2 left out: the codec is a randomly initialised" in report
    assert (tmp_path / "eval" / "train-step1" / "videos" / "long_000.mp4").exists()
  env = WorldModelEnv.from_model(model)
  frames = np.random.default_rng(0).integers(0, 256, (2, 1) + image_shape, np.uint8)
  env.reset(frames)
  new, *_ = env.step(np.zeros((2, 3, model.action_stats.action_dim), np.float32))
  assert new.shape == (2, 3) + image_shape and np.isfinite(np.asarray(new)).all()


@pytest.mark.parametrize("recipe", READ_HERE)
def test_recipe_reads_its_dataset(recipe, builders):
  """The recipe's dataset, read as its training run reads it: checked against its model (what
  `wmjax train` checks before compiling), training windows of its frames, resolution and action
  width, and finite normalised evaluation windows."""
  config = _config(recipe, builders)
  data = build_data(config)
  (member,) = data.members
  assert member.spec.name == config.data.dataset
  assert member.spec.action_dim == config.model.action_dim
  frames, image_shape = config.data.frames, tuple(config.data.resolution) + (3,)
  # the fixture episodes of 5, 3 and 7 steps, windows of 4 frames at stride 1
  assert len(member.train) == 2 + 4
  window = member.train[0]
  assert window["frames"].shape == (frames,) + image_shape
  assert window["actions"].shape == (frames - 1, config.model.action_dim)
  windows = eval_windows(data, config)
  assert windows["frames"].shape == (2, frames) + image_shape
  assert np.isfinite(windows["actions"]).all()


def test_pre_encoded_latents_train_like_frames(builders, tmp_path, capsys):
  recipe = str(ROOT / "configs" / "bridge.py") + ":tiny"
  overrides = [f"--config.data.builder_dir={builders['bridge']}"]
  out = tmp_path / "latents"
  assert cli.main(["data", "encode", "--config", recipe, "--out", str(out), "--splits", "train"]
                  + overrides) == 0
  episodes = LatentEpisodes(str(out), "train")
  assert list(episodes.lengths()) == list(oxe_fixtures.EPISODE_LENGTHS)
  episode = episodes.episode(2, 1, 5)
  config = _config("bridge.py", builders)
  assert episode.images.shape == (4,) + tuple(config.frame_shape)
  assert episode.actions.shape == (4, 7)
  # the stored latents are the codec's encoding of the resized frames (a random VAE of the same
  # layout and widths has the same weights on every build)
  codec = make_codec(config.codec)
  raw = ArrayRecordEpisodes(builders["bridge"], "train").episode(2)
  window = make_window(raw, 1, 4, tuple(config.data.resolution))
  expected = codec.encode(to_model(window["frames"]))
  np.testing.assert_allclose(episode.images.astype(np.float32), expected, atol=2e-2, rtol=1e-2)

  latent_config = _config("bridge.py", builders, **{"data.latents_dir": str(out)})
  _, result = train(latent_config, str(tmp_path / "run"))
  assert result["step"] == 1 and np.isfinite(result["val_loss"])
  wrong = _config("bridge.py", builders, **{"data.latents_dir": str(out), "codec.sample": True})
  with pytest.raises(ValueError, match="was encoded with codec"):
    train(wrong, str(tmp_path / "wrong"))
  one_line_error(capsys, ["data", "encode", "--config", recipe, "--out", str(out)] + overrides,
                 "never overwritten")
  assert not os.path.exists(str(out) + ".incomplete")


def test_rlds_config_reads_three_episodes_with_its_default_splits(builders):
  """configs/rlds.py as the README's own-data command sets it up: 2-frame windows of its own, and
  its default splits (train[:90%] / train[90%:]) hold out one of three episodes. The same config
  trains and evaluates from the command line in
  test_data_specs.py::test_own_lerobot_data_from_import_to_evaluation."""
  builder = builders["fractal20220817_data"]
  config = load_config(str(ROOT / "configs" / "rlds.py"), [f"{k}={v!r}" for k, v in {
      "data.builder_dir": builder, "data.dataset": "fractal20220817_data",
      "model.action_dim": 7, "data.resolution": (16, 16), "frame_shape": (16, 16, 3)}.items()])
  data = build_data(config)  # what `wmjax train` checks against the model before compiling
  (member,) = data.members
  assert member.spec.name == "fractal20220817_data" and member.spec.action_dim == 7
  assert len(member.train.episodes) == 2 and len(member.eval.episodes) == 1
  assert member.train[0]["frames"].shape == (2, 16, 16, 3)
  assert eval_windows(data, config)["frames"].shape[1:] == (2, 16, 16, 3)


def test_every_shipped_config_is_trained_by_a_test():
  files = {os.path.basename(p) for p in glob.glob(str(ROOT / "configs" / "*.py"))}
  covered = set(RECIPES) | set(READ_HERE) | set(TRAINED_ELSEWHERE)
  covered_files = {c.split(":")[0] for c in covered}
  assert files <= covered_files, f"configs no test trains: {sorted(files - covered_files)}"
  spec = importlib.util.spec_from_file_location("pusht_config", ROOT / "configs" / "pusht.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  profiles = {f"pusht.py:{p}" for p in module.PROFILES}
  assert profiles <= covered, f"profiles no test trains: {sorted(profiles - covered)}"


def test_own_data_mistakes_end_in_one_line(builders, tmp_path, capsys):
  """Each mistake a newcomer's own data or flags can make: one line on stderr, exit 2, before
  anything compiles."""
  builder = builders["fractal20220817_data"]
  train = ["train", "--config", str(ROOT / "configs" / "rlds.py"), "--workdir", str(tmp_path / "w"),
           f"--config.data.builder_dir={builder}", "--config.data.dataset='fractal20220817_data'",
           "--config.model.action_dim=7"]
  one_line_error(capsys, train + ["--config.data.image_key='wrist'"],
                 r"match no known layout.*'wrist'")
  one_line_error(capsys, train + ["--config.data.train_split='valid'"],
                 r"has no split 'valid'; splits: \['train'\]")
  one_line_error(capsys, train + ["--config.data.spec.action_keys=('action/nope',)"],
                 r"match no known layout.*'action/nope'")
  one_line_error(capsys, train + ["--config.data.frames=9"], "exceeds model.num_frames")
  one_line_error(capsys, ["data", "stats", builder, "--split", "valid"], "has no split 'valid'")
  one_line_error(capsys, ["data", "convert", builder, str(tmp_path / "out")],
                 "is stored as array_record, not tfrecord")
  one_line_error(capsys, ["train", "--config", str(ROOT / "configs" / "wpe_600m.py"),
                          "--workdir", str(tmp_path / "m")], "names no dataset: a model-only config")
  assert not list(tmp_path.glob("w/checkpoints/*"))  # nothing was trained
