"""``wmjax data``: prepare, convert, encode, summarise and import datasets."""

from __future__ import annotations

import argparse
import dataclasses
import json

from wmjax.cli import common
from wmjax.config import load_config


def prepare(args, extra) -> int:
  """Generate a dataset (gridworld, or Push-T from the gym-pusht simulator) as an RLDS TFDS
  dataset in ArrayRecord, once per parameter set; prints the builder directory."""
  del extra
  from wmjax import registry
  generated = registry.generated_datasets()[args.dataset]  # its task is imported: _add_prepare
  fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(generated.params)}
  print(generated.prepare(args.data_dir, generated.params(**fields)))
  return 0


def convert(args, extra) -> int:
  """Rewrite a TFRecord RLDS dataset (TFDS builder directory) as ArrayRecord."""
  del extra
  from wmjax.data.convert import convert_to_array_record
  print(convert_to_array_record(args.src, args.dst))
  return 0


def encode(args, extra) -> int:
  """Encode a dataset's episodes with the config's codec into ArrayRecord latents (IRASim's
  pre-encoding); train from them with --config.data.latents_dir=OUT."""
  from wmjax.train.encode import encode_latents
  config = load_config(args.config, common.overrides(extra))
  splits = args.splits.split(",") if args.splits else None
  print(encode_latents(config, args.out, splits, dataset=args.dataset, seed=args.seed))
  return 0


def train_codec(args, extra) -> int:
  """Fit a small AutoencoderKL to the frames of the config's dataset and write it as a diffusers
  folder (with wmjax_codec.json: held-out reconstruction metrics, the latent shape and the
  --config overrides that train a world model on it; and reconstructions.png). Use it with
  --config.codec.kind=vae --config.codec.path=OUT."""
  from wmjax.train.codec import CodecRecipe, train_codec as fit
  config = load_config(args.config, common.overrides(extra))
  recipe = CodecRecipe(**{f.name: getattr(args, f.name) for f in dataclasses.fields(CodecRecipe)})
  report = fit(config, args.out, recipe)
  print(json.dumps({k: report[k] for k in ("held_out", "latent_shape", "overrides")}, indent=2))
  return 0


def stats(args, extra) -> int:
  """Compute (or show the cached) action statistics of a dataset split (cached per split and
  spec: those of train[:95%] are of exactly those episodes)."""
  del extra
  from wmjax.data.sources import action_stats
  result = action_stats(args.builder_dir, args.split, args.name, recompute=args.recompute)
  print(json.dumps(dict(result.to_dict(), split=args.split), indent=2))
  return 0


def inspect(args, extra) -> int:
  """Print a prepared TFDS dataset's splits and features, and a suggested dataset spec
  (config.data.spec) to train on it with no code."""
  del extra
  from wmjax.data.describe import describe
  from wmjax.data.sources import check_shards, open_builder
  builder = open_builder(args.builder_dir)
  check_shards(builder, args.builder_dir)
  print(describe(builder))
  return 0


def import_lerobot(args, extra) -> int:
  """Import a local LeRobot dataset (meta/info.json, data/**/*.parquet, videos/**/*.mp4; v2.x or
  v3 layout) as an RLDS dataset in ArrayRecord; prints the builder directory. Train on it with
  configs/rlds.py and --config.data.builder_dir=OUT."""
  del extra
  from wmjax.data.lerobot import import_lerobot as run_import
  print(run_import(args.src, args.out, camera=args.camera, action_key=args.action_key))
  return 0


def import_irasim(args, extra) -> int:
  """Import one dataset directory of IRASim's benchmark data (annotation/<split>/*.json with the
  videos they name; rt1, bridge or languagetable) as an RLDS dataset in ArrayRecord, splits
  train / val / test as IRASim has them (its evaluation reads test); prints the builder
  directory."""
  del extra
  from wmjax.data.irasim import import_irasim as run_import
  print(run_import(args.src, args.out, dataset=args.dataset, camera=args.camera))
  return 0


def import_wpe(args, extra) -> int:
  """Import WPE / WorldGym episodes (<subset>/<split>/NNNNNNNNN.mp4 beside NNNNNNNNN.npz, as its
  download_data.py writes them) as an RLDS dataset in ArrayRecord, the chosen subsets pooled
  into the splits train and test; prints the builder directory."""
  del extra
  from wmjax.data.wpe import import_wpe as run_import
  subsets = [s for s in args.subsets.split(",") if s] if args.subsets else None
  print(run_import(args.src, args.out, subsets=subsets))
  return 0


def _tuple_of(kind: type):
  """Comma-separated numbers -> a tuple of ``kind``."""
  def parse(text: str) -> tuple:
    try:
      return tuple(kind(part) for part in text.split(",") if part.strip())
    except ValueError:
      raise argparse.ArgumentTypeError(
          f"expected comma-separated {kind.__name__}s, got {text!r}") from None
  return parse


def _bool(text: str) -> bool:
  value = text.strip().lower()
  if value not in ("true", "false", "1", "0"):
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
  return value in ("true", "1")


def _add_fields(parser, params, what: str) -> None:
  """One flag per field of the dataclass ``params`` (tuples as comma-separated numbers)."""
  for field in dataclasses.fields(params):
    parse = (_tuple_of(type(field.default[0]) if field.default else float)
             if isinstance(field.default, tuple) else
             _bool if isinstance(field.default, bool) else type(field.default))
    shown = ",".join(map(str, field.default)) if isinstance(field.default, tuple) else field.default
    parser.add_argument(f"--{field.name}", type=parse, default=field.default,
                        help=f"{what} {field.name} (default {shown})")


def _add_prepare(data_sub) -> None:
  """``data prepare NAME``: one subcommand per generated dataset of the built-in tasks, one flag
  per field of its parameter dataclass."""
  from wmjax.config import BUILT_IN_TASKS, import_task
  parser = data_sub.add_parser("prepare", help="generate a dataset (RLDS, ArrayRecord)",
                               description=prepare.__doc__)
  prepare_sub = parser.add_subparsers(dest="dataset", required=True)
  generated = {name: d for module in BUILT_IN_TASKS.values()
               for name, d in import_task(module).datasets.items()}
  for name, made in generated.items():
    dataset = prepare_sub.add_parser(name, help=f"generate the {name} dataset",
                                     description=prepare.__doc__)
    dataset.add_argument("--data_dir", required=True, help="TFDS data directory to write into")
    _add_fields(dataset, made.params, name)
    common.register(dataset, prepare, host_only=True)


def add_parser(sub) -> None:
  """The ``data`` command group."""
  data = sub.add_parser("data", help="prepare, convert, encode, summarise and import datasets")
  data_sub = data.add_subparsers(dest="data_command", required=True)
  _add_prepare(data_sub)

  parser = data_sub.add_parser("convert", help="TFRecord RLDS -> ArrayRecord (no beam)",
                               description=convert.__doc__)
  parser.add_argument("src", help="builder directory, e.g. gs://gresearch/robotics/bridge/0.1.0")
  parser.add_argument("dst", help="output builder directory (must not exist)")
  common.register(parser, convert, host_only=True)

  parser = data_sub.add_parser("encode", help="pre-encode a dataset with the config's codec",
                               description=encode.__doc__)
  parser.add_argument("--config", required=True, help=common.CONFIG_HELP)
  parser.add_argument("--out", required=True, help="output directory (must not exist)")
  parser.add_argument("--splits", default=None,
                      help="comma-separated splits (default: the config's train and eval splits)")
  parser.add_argument("--dataset", default=None, help="the mixture member to encode")
  parser.add_argument("--seed", type=int, default=0, help="for codecs that sample latents")
  common.register(parser, encode, takes_overrides=True)

  from wmjax.train.codec import CodecRecipe
  parser = data_sub.add_parser("train-codec", help="fit an AutoencoderKL to a dataset's frames",
                               description=train_codec.__doc__)
  parser.add_argument("--config", required=True, help=common.CONFIG_HELP)
  parser.add_argument("--out", required=True, help="output folder (new or empty)")
  _add_fields(parser, CodecRecipe, "codec")
  common.register(parser, train_codec, takes_overrides=True)

  parser = data_sub.add_parser("stats", help="action statistics, cached as JSON beside the data",
                               description=stats.__doc__)
  parser.add_argument("builder_dir")
  parser.add_argument("--split", default="train")
  parser.add_argument("--name", default=None, help="dataset spec name (default: the builder's)")
  parser.add_argument("--recompute", action="store_true")
  common.register(parser, stats, host_only=True)

  parser = data_sub.add_parser("inspect", help="features of a TFDS dataset and a suggested spec",
                               description=inspect.__doc__)
  parser.add_argument("builder_dir")
  common.register(parser, inspect, host_only=True)

  parser = data_sub.add_parser("import", help="bring another format in as RLDS (ArrayRecord)",
                               description="Import a LeRobot, IRASim or WPE dataset as RLDS in "
                                           "ArrayRecord (the form training reads).")
  import_sub = parser.add_subparsers(dest="format", required=True)
  lerobot = import_sub.add_parser("lerobot", help="a local LeRobot dataset (v2.x or v3)",
                                  description=import_lerobot.__doc__)
  lerobot.add_argument("src", help="LeRobot dataset directory (with meta/info.json)")
  lerobot.add_argument("out", help="output builder directory (must not exist)")
  lerobot.add_argument("--camera", default=None,
                       help="camera feature stored as observation/image, e.g. "
                            "observation.images.top (default: the first); every other camera "
                            "is kept as observation/<name>")
  lerobot.add_argument("--action_key", default="action",
                       help="the feature stored as the action (default: action)")
  common.register(lerobot, import_lerobot, host_only=True)

  irasim = import_sub.add_parser("irasim", help="an IRASim benchmark dataset (rt1, bridge, "
                                 "languagetable)", description=import_irasim.__doc__)
  irasim.add_argument("src", help="one dataset directory, e.g. opensource_robotdata/rt1 (with "
                                  "annotation/<split>/*.json)")
  irasim.add_argument("out", help="output builder directory (must not exist)")
  irasim.add_argument("--dataset", default=None, choices=("rt1", "bridge", "droid",
                                                          "languagetable"),
                      help="which IRASim dataset SRC holds (default: SRC's name)")
  irasim.add_argument("--camera", type=int, default=0,
                      help="RT-1 / Bridge: the annotation's video stored as observation/image "
                           "(default 0, as IRASim)")
  common.register(irasim, import_irasim, host_only=True)

  wpe = import_sub.add_parser("wpe", help="WPE / WorldGym episodes (mp4 + npz)",
                              description=import_wpe.__doc__)
  wpe.add_argument("src", help="download_data.py's output directory (or one subset of it)")
  wpe.add_argument("out", help="output builder directory (must not exist)")
  wpe.add_argument("--subsets", default=None,
                   help="comma-separated subsets to pool, e.g. rt_1,bridge_v2 (default: all)")
  common.register(wpe, import_wpe, host_only=True)
