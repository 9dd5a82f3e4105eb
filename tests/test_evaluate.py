"""Evaluation tools: video files, user inputs, the protocols, and `wmjax evaluate` / `wmjax rollout`
on the suite's tiny gridworld model (conftest.py)."""

import csv
import json
import os
import shutil
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from conftest import ROOT, one_line_error, tiny_world_model
from wmjax import cli
from wmjax.codecs import PixelCodec
from wmjax.config import load_config
from wmjax.data.stats import ActionStats
from wmjax.eval import inputs, protocols, video
from wmjax.eval.calibration import with_float8_scales
from wmjax.eval.frechet import FrechetDistances
from wmjax.eval.rollouts import run_rollouts
from wmjax.eval.trajectories import Trajectories
from wmjax.model import LoadedModel, load_model
from wmjax.rollout import rollout
from wmjax.tasks.gridworld import dataset as gridworld

# ----------------------------------------------------------------------------- video files


@pytest.mark.unit
def test_mp4_and_gif_round_trip_and_panels():
  rng = np.random.default_rng(0)
  truth = np.zeros((5, 16, 16, 3), np.uint8)
  for t in range(5):
    truth[t, 4 + t:9 + t, 3:12] = (255, 64, 64)
  pred = np.roll(truth, 2, axis=2)
  panels = video.comparison(truth, pred)
  assert panels.shape == (5, 16, 3 * 16 + 2 * 2, 3)
  np.testing.assert_array_equal(panels[:, :, 36:], video.difference(pred, truth))
  np.testing.assert_array_equal(panels[:, :, 16:18], 255)  # white gaps
  for extension in (".mp4", ".gif"):
    path = video.write_video(f"/tmp/wmjax_test_video{extension}", panels, fps=4, scale=4)
    back = video.read_video(path).astype(int)
    expected = panels.repeat(4, 1).repeat(4, 2).astype(int)
    assert back.shape == expected.shape
    # GIF is lossless for these few colours; H.264 is lossy
    assert np.abs(back - expected).mean() < (0.5 if extension == ".gif" else 6.0)
  odd = video.write_video("/tmp/wmjax_test_odd.mp4", rng.integers(0, 255, (3, 9, 7, 3), np.uint8),
                          scale=1)
  assert video.read_video(odd).shape == (3, 10, 8, 3)  # padded to even sizes for yuv420p
  grid = video.frame_grid([truth, pred], scale=1)
  assert grid.shape == (2 * 16 + 2, 5 * 16 + 4 * 2, 3)
  with pytest.raises(ValueError, match="must end in one of"):
    video.write_video("/tmp/x.avi", panels)
  with pytest.raises(ValueError, match="same frames and height"):
    video.side_by_side(truth, truth[:3])


@pytest.mark.unit
def test_gif_needs_no_ffmpeg_and_mp4_says_what_it_needs(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as where it is not installed
  frames = np.zeros((3, 8, 8, 3), np.uint8)
  frames[np.arange(3), np.arange(3)] = 255  # distinct frames (Pillow merges repeated ones)
  assert video.read_video(video.write_video(str(tmp_path / "a.gif"), frames)).shape[0] == 3
  with pytest.raises(ImportError, match="pip install imageio-ffmpeg.*GIF"):
    video.write_video(str(tmp_path / "a.mp4"), frames)


# ----------------------------------------------------------------------------- user inputs


@pytest.mark.unit
def test_read_frames_and_actions(tmp_path):
  frame = np.random.default_rng(0).integers(0, 256, (16, 16, 3), np.uint8)
  Image.fromarray(frame).save(tmp_path / "a.png")
  Image.fromarray(frame[:, ::-1]).save(tmp_path / "b.png")
  frames = inputs.read_frames([str(tmp_path / "a.png"), str(tmp_path / "b.png")], (16, 16, 3))
  assert frames.shape == (1, 2, 16, 16, 3)
  np.testing.assert_array_equal(frames[0, 1], frame[:, ::-1])
  np.save(tmp_path / "f.npy", frame.astype(np.float32) / 127.5 - 1.0)
  np.testing.assert_array_equal(inputs.read_frames([str(tmp_path / "f.npy")], (16, 16, 3))[0, 0],
                                frame)
  with pytest.raises(ValueError, match=r"frames are 16x16 but the model was trained on 8x8"):
    inputs.read_frames([str(tmp_path / "a.png")], (8, 8, 3))
  assert inputs.read_frames([str(tmp_path / "a.png")], (8, 8, 3), resize=True).shape == (
      1, 1, 8, 8, 3)
  np.save(tmp_path / "bad.npy", np.full((16, 16, 3), 3.0, np.float32))
  with pytest.raises(ValueError, match=r"uint8 or finite floats in \[-1, 1\]"):
    inputs.read_frames([str(tmp_path / "bad.npy")], (16, 16, 3))
  with pytest.raises(ValueError, match="image files"):
    inputs.read_frames([str(tmp_path / "a.txt")], (16, 16, 3))

  with open(tmp_path / "a.csv", "w", newline="") as f:
    csv.writer(f).writerows([["dy0", "dx0"], [0.5, -1], [1, 2], [3, 4]])
  np.testing.assert_array_equal(inputs.read_actions(str(tmp_path / "a.csv"), 2),
                                [[[0.5, -1], [1, 2], [3, 4]]])
  with pytest.raises(ValueError, match=r"the model takes 4-dim actions, the file has 2"):
    inputs.read_actions(str(tmp_path / "a.csv"), 4)
  np.save(tmp_path / "nan.npy", np.array([[np.nan, 1.0]]))
  with pytest.raises(ValueError, match="NaN or inf"):
    inputs.read_actions(str(tmp_path / "nan.npy"), 2)
  np.save(tmp_path / "empty.npy", np.zeros((0, 2)))
  with pytest.raises(ValueError, match=r"N >= 1"):
    inputs.read_actions(str(tmp_path / "empty.npy"), 2)


# ----------------------------------------------------------------------------- protocols


def _loaded(wm, params, config_name="irasim.py:S"):
  config = load_config(str(ROOT / "configs" / config_name))
  stats = ActionStats.compute(np.random.default_rng(0).normal(size=(50, 7)), "toy", None)
  return LoadedModel(config, wm, params, stats, 0, PixelCodec())


@pytest.mark.unit
@pytest.mark.slow
def test_run_rollouts_scores_only_real_frames():
  """Trajectories of different lengths padded together: frames past the end are NaN, the copy-last
  baseline is exact, and the mean of a trajectory covers its own frames only."""
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                                frame_shape=(16, 16, 3))
  rng = np.random.default_rng(0)
  windows = [{"frames": rng.integers(0, 256, (n, 16, 16, 3), np.uint8),
              "actions": rng.normal(size=(n - 1, 7)).astype(np.float32), "episode": i,
              "start": 0, "instruction": b""} for i, n in enumerate((7, 4, 6))]
  trajectories = Trajectories.stack(windows, lambda a: a)
  assert trajectories.frames.shape == (3, 7, 16, 16, 3) and list(trajectories.lengths) == [7, 4, 6]
  outcome = run_rollouts(_loaded(wm, params), trajectories, first=0, context=1,
                         horizon=3, rng=jax.random.key(0), batch_size=2, keep_videos=3)
  mse = outcome.model["mse"]
  assert mse.shape == (3, 6)
  assert np.isfinite(mse[0]).all() and np.isnan(mse[1, 3:]).all() and np.isfinite(mse[1, :3]).all()
  copy = outcome.copy_last["mse"]
  truth = trajectories.frames.astype(np.float64) / 255
  np.testing.assert_allclose(copy[1, :3], ((truth[1, 1:4] - truth[1, :1]) ** 2).mean((1, 2, 3)),
                             rtol=1e-5)
  assert [v[1].shape[0] for v in outcome.videos] == [7, 4, 6]
  summary = outcome.summary()
  per_trajectory = [np.nanmean(m) for m in mse]
  assert abs(summary["model"]["mse"]["mean"] - np.mean(per_trajectory)) < 1e-9
  assert len(summary["model"]["mse"]["per_frame"]) == 6


@pytest.mark.unit
def test_sweep_settings_vary_one_axis_at_a_time():
  assert protocols.sweep_settings(20, 9, 9) == [(1, 9), (2, 9), (4, 9), (8, 9), (9, 1), (9, 2),
                                                (9, 4), (9, 8), (9, 9)]
  assert protocols.sweep_settings(6, 1, 5) == [(1, 1), (1, 2), (1, 4), (1, 5)]


def mean_colour_features(frames):
  """A stand-in feature network for FID: frames [N, H, W, 3] -> [N, 3]."""
  return frames.mean((1, 2))


def colour_trajectory_features(clips):
  """A stand-in feature network for FVD: clips [N, T, H, W, 3] -> [N, T * 3]."""
  return clips.mean((2, 3)).reshape(len(clips), -1)


@pytest.mark.unit
def test_frechet_distances_from_user_feature_networks():
  rng = np.random.default_rng(0)
  clips = rng.integers(0, 256, (12, 4, 8, 8, 3), np.uint8)
  same = FrechetDistances(mean_colour_features, colour_trajectory_features)
  same.update(clips[:6], clips[:6])
  same.update(clips[6:], clips[6:])
  assert max(abs(v) for v in same.result().values()) < 1e-6
  brighter = FrechetDistances(mean_colour_features, None)
  brighter.update(clips, np.clip(clips.astype(int) + 40, 0, 255).astype(np.uint8))
  result = brighter.result()
  assert set(result) == {"fid"} and result["fid"] > 0.01


# ----------------------------------------------------------------------------- commands


@pytest.fixture
def workdir(trained_workdir):
  """The suite's tiny gridworld model (conftest.py): 6-frame windows, checkpoints 2 and 4, 2
  held-out episodes of 12 steps."""
  return str(trained_workdir)


@pytest.mark.integration
@pytest.mark.slow
def test_load_model_reads_ema_or_raw_parameters(workdir):
  ema = load_model(workdir)
  raw = load_model(workdir, params="raw", step=2, overrides=["sampling.num_steps=3"])
  assert ema.step == 4 and raw.step == 2 and raw.config.sampling.num_steps == 3
  difference = jax.tree.map(lambda a, b: float(np.abs(a - b).max()), ema.params, raw.params)
  assert max(jax.tree.leaves(difference)) > 0
  half = load_model(workdir, param_dtype="bfloat16")
  assert {leaf.dtype for leaf in jax.tree.leaves(half.params)} == {jnp.dtype("bfloat16")}
  frames = half.codec.encode(jnp.zeros((1, 1, 16, 16, 3)))
  assert np.isfinite(np.asarray(rollout(half.world_model, half.params, frames,
                                        jnp.zeros((1, 2, 4)), jax.random.key(0),
                                        horizon=2))).all()
  with pytest.raises(ValueError, match=r"no checkpoint for step 3"):
    load_model(workdir, step=3)
  with pytest.raises(FileNotFoundError, match="holds no checkpoints"):
    load_model(os.path.dirname(workdir))


@pytest.mark.integration
@pytest.mark.slow
def test_evaluate_command_writes_metrics_report_and_videos(workdir, tmp_path, capsys):
  out = tmp_path / "eval"
  assert cli.main(["evaluate", "--workdir", workdir, "--out", str(out), "--sets", "2",
                   "--videos", "2", "--sweep_frames", "4",
                   "--frame_features", "test_evaluate:mean_colour_features",
                   "--clip_features", "test_evaluate:colour_trajectory_features"]) == 0
  # stderr is no terminal here (as in a batch job's log): plain progress lines, no bars
  printed = capsys.readouterr()
  for line in ("evaluate short: 4/4 trajectories", "evaluate long: 2/2 trajectories",
               "evaluate sweep: 8/8 rollout sets"):
    assert line in printed.out, line
  assert "\r" not in printed.out + printed.err
  results = json.loads((out / "metrics.json").read_text())
  short, long = results["short"], results["long"]
  assert short["horizon"] == 5 and short["trajectories"] == 2 * 2  # 12 steps -> 2 windows of 6
  assert set(short["frechet"]) == {"fid", "fvd"} and short["frechet"]["fid"] >= 0
  assert long["trajectories"] == 2 and len(long["model"]["mse"]["per_frame"]) == 11
  for protocol in (short, long):
    for name in ("mse", "psnr", "ssim", "gray_psnr", "gray_ssim", "latent_l2", "masked_mse",
                 "square_error_px"):
      assert np.isfinite(protocol["model"][name]["mean"]), name
      assert np.isfinite(protocol["copy_last"][name]["mean"]), name
  settings = [(r["context"], r["horizon"]) for r in results["sweep"]["rows"]]
  assert settings == [(1, 1), (1, 2), (1, 4), (1, 5)]
  assert all(r["sets"] == 2 and r["mse"]["stderr"] is not None for r in results["sweep"]["rows"])
  report = (out / "report.md").read_text()
  assert "IRASim short trajectories" in report and "WPE context / horizon sweep" in report
  clip = video.read_video(str(out / "videos" / "short_000.mp4"))
  assert clip.shape[0] == 6 and clip.shape[2] > 3 * clip.shape[1] - 16  # three panels
  assert (out / "videos" / "long_001.png").exists()


@pytest.mark.integration
@pytest.mark.slow
def test_evaluate_with_float8_matmuls_calibrates_on_the_training_split(workdir, tmp_path):
  """``--config.model.fp8_matmuls=True``: static float8 scales from training windows (how close
  a calibrated network stays to the full-precision one: tests/test_float8.py)."""
  out = tmp_path / "fp8"
  assert cli.main(["evaluate", "--workdir", workdir, "--out", str(out), "--protocols", "short",
                   "--videos", "0", "--config.model.fp8_matmuls=True"]) == 0
  results = json.loads((out / "metrics.json").read_text())
  assert results["float8"] == "static float8 scales from windows of the 'train' split"
  assert np.isfinite(results["short"]["model"]["mse"]["mean"])
  # a model whose training data is not on this machine keeps per-token scales, and says why
  model = load_model(workdir, overrides=["model.fp8_matmuls=True", "data.dataset='bridge'",
                                         f"data.builder_dir={str(tmp_path / 'gone')!r}"])
  same, why = with_float8_scales(model, jax.random.key(0))
  assert same.params is model.params and "per-token float8 scales" in why and "gone" in why


@pytest.mark.integration
@pytest.mark.slow
def test_short_protocol_chains_blocks_beyond_the_window(workdir, tmp_path):
  """``rollout.short_actions`` longer than the 6-frame window: 1 frame + 7 actions, generated in
  chained blocks of 5, every one of the 7 frames scored."""
  out = tmp_path / "eval"
  assert cli.main(["evaluate", "--workdir", workdir, "--out", str(out), "--protocols", "short",
                   "--videos", "0", "--config.rollout.short_actions=7"]) == 0
  short = json.loads((out / "metrics.json").read_text())["short"]
  assert short["actions"] == 7 and short["horizon"] == 5
  assert short["trajectories"] == 2  # 12 steps -> 1 window of 8 per episode
  assert len(short["model"]["square_error_px"]["per_frame"]) == 7
  # without --split: the config's evaluation split (an imported dataset may hold out train[k:])
  held_out = tmp_path / "held_out"
  assert cli.main(["evaluate", "--workdir", workdir, "--out", str(held_out), "--protocols",
                   "short", "--videos", "0", "--config.rollout.short_actions=7",
                   "--config.data.eval_split='train[:3]'"]) == 0
  metrics = json.loads((held_out / "metrics.json").read_text())
  assert metrics["split"] == "train[:3]" and metrics["short"]["trajectories"] == 3


@pytest.mark.integration
@pytest.mark.slow
def test_rollout_command_applies_the_checkpoint_normalisation(workdir, tmp_path, capsys):
  model = load_model(workdir)
  config = gridworld.GridworldConfig(num_squares=2, image_size=16, square_size=4)
  centres, raw_actions = gridworld.simulate(config, np.random.default_rng(5))
  Image.fromarray(gridworld.render(centres[0], config)).save(tmp_path / "start.png")
  with open(tmp_path / "actions.csv", "w", newline="") as f:
    csv.writer(f).writerows([["vy0", "vx0", "vy1", "vx1"]] + raw_actions[:7].tolist())
  out = tmp_path / "out"
  assert cli.main(["rollout", "--workdir", workdir, "--frames", str(tmp_path / "start.png"),
                   "--actions", str(tmp_path / "actions.csv"), "--out", str(out),
                   "--seed", "3"]) == 0
  frames = np.load(out / "frames.npy")
  assert frames.shape == (1, 8, 16, 16, 3)
  start = gridworld.render(centres[0], config)[None, None].astype(np.float32) / 127.5 - 1.0
  normalised = model.action_stats.normalize(raw_actions[None, :7], "mean_std")
  expected = rollout(model.world_model, model.params, start, normalised,
                     jax.random.split(jax.random.key(3))[1], horizon=5)
  np.testing.assert_array_equal(frames, np.round((np.asarray(expected) + 1) * 127.5).astype(
      np.uint8))
  for name in ("rollout.mp4", "rollout.gif", "grid.png"):
    assert (out / name).stat().st_size > 0
  np.save(tmp_path / "wrong.npy", raw_actions[:5, :3])
  one_line_error(capsys, ["rollout", "--workdir", workdir, "--frames",
                          str(tmp_path / "start.png"), "--actions", str(tmp_path / "wrong.npy"),
                          "--out", str(out)], "the model takes 4-dim actions, the file has 3")
  with pytest.raises(ValueError, match="the model takes 4-dim actions"):  # --debug: the traceback
    cli.main(["rollout", "--debug", "--workdir", workdir, "--frames", str(tmp_path / "start.png"),
              "--actions", str(tmp_path / "wrong.npy"), "--out", str(out)])


@pytest.mark.integration
@pytest.mark.slow
def test_checkpoints_from_before_a_config_field_take_its_override(workdir, tmp_path):
  """A checkpoint whose stored config predates sampling.kv_cache and model.attention_impl loads
  with their defaults, and the new fields can be overridden."""
  old = tmp_path / "old"
  shutil.copytree(workdir, old)
  for metadata in old.glob("checkpoints/*/config/metadata"):
    stored = json.loads(metadata.read_text())
    del stored["sampling"]["kv_cache"], stored["model"]["attention_impl"]
    metadata.write_text(json.dumps(stored))
  assert load_model(str(old)).world_model.sampler.kv_cache is False
  model = load_model(str(old), overrides=["sampling.kv_cache=True"])
  assert model.world_model.sampler.kv_cache and model.world_model.network.attention_impl == "xla"
