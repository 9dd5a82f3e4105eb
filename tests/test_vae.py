"""The Flax AutoencoderKL against diffusers' PyTorch implementation (random weights, SD/SDXL and
SD3 layouts), weight-file errors, and the codecs."""

import dataclasses
import json
import shutil
import typing

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import safetensors.numpy

from conftest import ROOT, gridworld_config, gridworld_overrides, jit_apply, one_line_error
from wmjax.codecs import PatchCodec, PixelCodec, codec_config, make_codec
from wmjax.config import CodecConfig
from wmjax.nn.vae import LAYOUTS, load_diffusers, random_vae, save_diffusers
from wmjax.train.data import build_data

pytestmark = pytest.mark.unit


@pytest.fixture
def save_random_vae(diffusers):
  """vae_fixtures.save_random_vae (imported with torch and diffusers, which it needs)."""
  import vae_fixtures
  return vae_fixtures.save_random_vae


def _relative_error(ours, theirs):
  return float(np.linalg.norm(np.asarray(ours) - theirs) / np.linalg.norm(theirs))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.slow
def test_encode_and_decode_match_diffusers(tmp_path, layout, torch, save_random_vae):
  vae = save_random_vae(tmp_path / layout, layout)
  module, params = load_diffusers(str(tmp_path / layout))
  x = np.random.default_rng(0).uniform(-1, 1, (2, 32, 24, 3)).astype(np.float32)
  with torch.no_grad():
    posterior = vae.encode(torch.from_numpy(x).permute(0, 3, 1, 2)).latent_dist
    mean = posterior.mean.permute(0, 2, 3, 1).numpy()
    logvar = posterior.logvar.permute(0, 2, 3, 1).numpy()
    z = np.random.default_rng(1).normal(size=mean.shape).astype(np.float32)
    decoded = vae.decode(torch.from_numpy(z).permute(0, 3, 1, 2)).sample.permute(0, 2, 3, 1)
  apply = jit_apply(module)
  our_mean, our_logvar = apply(params, jnp.asarray(x), method="encode")
  assert our_mean.shape == mean.shape == (2, 16, 12, LAYOUTS[layout]["latent_channels"])
  assert _relative_error(our_mean, mean) < 1e-4
  assert _relative_error(our_logvar, logvar) < 1e-4
  assert _relative_error(apply(params, jnp.asarray(z), method="decode"),
                         decoded.numpy()) < 1e-4


@pytest.mark.slow
def test_vae_codec_applies_scaling_and_shift_over_video_axes(tmp_path, save_random_vae):
  save_random_vae(tmp_path / "sd3", "sd3")
  codec = make_codec(codec_config(kind="vae", path=str(tmp_path / "sd3"), chunk=3))
  assert (codec.scaling_factor, codec.shift_factor) == (1.5305, 0.0609)
  frames = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (2, 5, 32, 24, 3)), jnp.float32)
  latents = codec.encode(frames)
  assert latents.shape == (2, 5) + codec.latent_shape((32, 24, 3)) == (2, 5, 16, 12, 16)
  apply = jit_apply(codec.module)
  mean, _ = apply(codec.params, frames.reshape(-1, 32, 24, 3), method="encode")
  np.testing.assert_allclose(latents.reshape(mean.shape), (mean - 0.0609) * 1.5305, atol=1e-4)
  decoded = codec.decode(latents)
  expected = apply(codec.params, mean, method="decode")
  np.testing.assert_allclose(decoded.reshape(expected.shape), np.clip(expected, -1, 1), atol=1e-4)
  assert codec.image_shape((16, 12, 16)) == (32, 24, 3)
  sampling = make_codec(codec_config(kind="vae", path=str(tmp_path / "sd3"), sample=True))
  with pytest.raises(ValueError, match="pass an rng"):
    sampling.encode(frames)
  assert float(jnp.abs(sampling.encode(frames, jax.random.key(0)) - latents).max()) > 1e-3


def _rewrite(src, dst, edit):
  shutil.copytree(src, dst)
  path = dst / "diffusion_pytorch_model.safetensors"
  state = safetensors.numpy.load_file(str(path))
  edit(state)
  safetensors.numpy.save_file(state, str(path))
  return str(dst)


def test_weight_file_errors_name_the_parameter(tmp_path, save_random_vae):
  save_random_vae(tmp_path / "vae", "sdxl")
  key = "decoder.up_blocks.1.resnets.0.conv1.weight"
  missing = _rewrite(tmp_path / "vae", tmp_path / "missing", lambda s: s.pop(key))
  with pytest.raises(ValueError, match=r"lack 1 parameter.*up_blocks\.1\.resnets\.0\.conv1"):
    load_diffusers(missing)
  unknown = _rewrite(tmp_path / "vae", tmp_path / "unknown",
                     lambda s: s.update({"encoder.extra.weight": np.zeros(3, np.float32)}))
  with pytest.raises(ValueError, match=r"no parameter for.*encoder\.extra\.weight"):
    load_diffusers(unknown)
  shape = _rewrite(tmp_path / "vae", tmp_path / "shape",
                   lambda s: s.update({key: s[key][:, :-1]}))
  with pytest.raises(ValueError, match=r"up_blocks\.1\.resnets\.0\.conv1\.weight: shape"):
    load_diffusers(shape)
  legacy = _rewrite(tmp_path / "vae", tmp_path / "legacy", lambda s: s.update(
      {k.replace("to_q", "query"): s.pop(k) for k in list(s) if ".to_q." in k}))
  module, params = load_diffusers(legacy)  # old attention names are mapped
  assert module.config.latent_channels == 4
  config = json.loads((tmp_path / "vae" / "config.json").read_text())
  config["act_fn"] = "gelu"
  (tmp_path / "legacy" / "config.json").write_text(json.dumps(config))
  with pytest.raises(ValueError, match="unsupported act_fn 'gelu'"):
    load_diffusers(legacy)
  (tmp_path / "empty").mkdir()
  with pytest.raises(FileNotFoundError, match="no config.json"):
    load_diffusers(str(tmp_path / "empty"))


def test_pixel_and_patch_codecs():
  frames = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (2, 3, 8, 12, 3)), jnp.float32)
  patch = PatchCodec(4)
  latents = patch.encode(frames)
  assert latents.shape == (2, 3, 2, 3, 48) and patch.image_shape((2, 3, 48)) == (8, 12, 3)
  np.testing.assert_array_equal(latents[0, 0, 1, 2, :3], frames[0, 0, 4, 8])  # pixel (4, 8)
  np.testing.assert_array_equal(patch.decode(latents), frames)
  np.testing.assert_array_equal(PixelCodec().encode(frames), frames)
  with pytest.raises(ValueError, match="not divisible by the codec's patch size 5"):
    PatchCodec(5).latent_shape((8, 12, 3))
  with pytest.raises(ValueError, match="codec.kind must be one of"):
    make_codec(codec_config(kind="jpeg"))
  with pytest.raises(ValueError, match="needs codec.path"):
    make_codec(codec_config(kind="vae"))
  with pytest.raises(ValueError, match="'/no/sdxl-vae', which is not there; without the VAE, "
                                       "--config.codec.kind=pixel.*--config.codec.random_vae=sdxl"):
    make_codec(codec_config(kind="vae", path="/no/sdxl-vae"))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_a_random_vae_codec_reads_no_files(layout):
  """codec.random_vae: the layout's latent channels, scaling and shift, the same weights on
  every build (one module and parameters per process: equal codecs, one compiled encode), and
  the path left unread."""
  choices = typing.get_args(typing.get_type_hints(CodecConfig)["random_vae"])
  assert set(choices) == {""} | set(LAYOUTS)  # the schema's choices are the layouts
  config = codec_config(kind="vae", random_vae=layout, random_vae_widths=(8, 8, 16),
                        path="/no/vae")
  codec, again = make_codec(config), make_codec(config)
  channels = LAYOUTS[layout]["latent_channels"]
  assert codec.latent_shape((32, 24, 3)) == (8, 6, channels)
  assert (codec.scaling_factor, codec.shift_factor) == (
      LAYOUTS[layout]["scaling_factor"], LAYOUTS[layout].get("shift_factor", 0.0))
  for ours, theirs in zip(jax.tree.leaves(codec.params), jax.tree.leaves(again.params)):
    np.testing.assert_array_equal(ours, theirs)
  assert codec == again and hash(codec) == hash(again)
  copied = dataclasses.replace(codec, params=jax.tree.map(jnp.copy, codec.params))
  assert codec != copied and codec != dataclasses.replace(codec, chunk=codec.chunk + 1)
  frames = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (2, 3, 32, 24, 3)), jnp.float32)
  latents = codec.encode(frames)
  assert latents.shape == (2, 3, 8, 6, channels) and float(jnp.std(latents)) > 0
  assert codec.decode(latents).shape == frames.shape
  with pytest.raises(ValueError, match=r"widths must be one or more positive ints, got \(\)"):
    make_codec(codec_config(kind="vae", random_vae=layout, random_vae_widths=()))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_a_random_vae_has_the_parameters_of_its_diffusers_layout(tmp_path, layout,
                                                                 save_random_vae):
  """random_vae's network is the diffusers AutoencoderKL of that layout and widths (one ResNet a
  level, GroupNorm groups dividing every width): the same parameter names and shapes."""
  save_random_vae(tmp_path, layout, widths=(8, 12), layers_per_block=1, norm_num_groups=4)
  module, params = load_diffusers(str(tmp_path))
  random_module, random_params = random_vae(layout, (8, 12))
  assert random_module.config == module.config
  assert jax.tree.map(np.shape, random_params) == jax.tree.map(np.shape, params)


def test_a_saved_vae_reads_back_in_diffusers_and_wmjax(tmp_path, torch, diffusers):
  module, params = random_vae("sdxl", (8, 16), seed=3)
  save_diffusers(str(tmp_path / "vae"), module.config, params)
  again, read = load_diffusers(str(tmp_path / "vae"))
  assert again.config == module.config
  assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), params, read))
  theirs = diffusers.AutoencoderKL.from_pretrained(str(tmp_path / "vae"))
  z = np.random.default_rng(1).normal(size=(2, 4, 6, 4)).astype(np.float32)
  with torch.no_grad():
    decoded = theirs.decode(torch.from_numpy(z).permute(0, 3, 1, 2)).sample.permute(0, 2, 3, 1)
  assert _relative_error(jit_apply(module)(params, jnp.asarray(z), method="decode"),
                         decoded.numpy()) < 1e-4


@pytest.mark.slow
def test_train_codec_fits_frames_into_a_folder_that_codec_vae_reads(data_dir, tmp_path, capsys,
                                                                     caplog):
  from wmjax import cli
  out = tmp_path / "codec"
  argv = ["data", "train-codec", "--config", str(ROOT / "configs" / "gridworld.py"), "--out",
          str(out), "--widths", "8,16", "--steps", "40", "--batch_size", "8", "--train_frames",
          "96", "--eval_frames", "8", "--learning_rate", "3e-3"]
  argv += [f"--config.{o}" for o in gridworld_overrides(data_dir)]
  assert cli.main(argv) == 0
  assert "codec step 40:" in caplog.text  # progress shown, though the root logger is at WARNING
  report = json.loads((out / "wmjax_codec.json").read_text())
  assert report["latent_shape"] == [8, 8, 4] and report["recipe"]["widths"] == [8, 16]
  first, last = report["history"][0], report["history"][-1]
  assert last["reconstruction"] < 0.5 * first["reconstruction"]
  assert report["held_out_frames"] == 8 and np.isfinite(report["held_out"]["psnr"])
  assert (out / "reconstructions.png").stat().st_size > 0
  codec = make_codec(codec_config(kind="vae", path=str(out)))
  assert codec.scaling_factor == pytest.approx(report["scaling_factor"])
  frames = np.random.default_rng(0).uniform(-1, 1, (2, 3, 16, 16, 3)).astype(np.float32)
  assert codec.encode(frames).shape == (2, 3, 8, 8, 4)
  on_latents = gridworld_config(data_dir, **{"codec.kind": "'vae'", "codec.path": repr(str(out)),
                                             "frame_shape": "(8,8,4)", "model.in_channels": 4,
                                             "diffusion.object_weight": 1.0})
  with pytest.raises(ValueError, match="object_weight=0 with codec.kind='vae'"):
    build_data(on_latents)
  written = (out / "diffusion_pytorch_model.safetensors").read_bytes()
  one_line_error(capsys, argv, "already holds a codec")  # refused: nothing is replaced
  assert (out / "diffusion_pytorch_model.safetensors").read_bytes() == written
  assert not (tmp_path / "codec.incomplete").exists()  # written there, renamed when whole
  (tmp_path / "other").mkdir()
  (tmp_path / "other" / "notes.txt").write_text("mine")
  one_line_error(capsys, argv[:5] + [str(tmp_path / "other")] + argv[6:], "is not an empty folder")
