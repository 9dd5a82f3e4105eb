"""wmjax.checkpoints.torch_file: torch.save archives (written here by torch) read without torch:
tensors exactly as torch holds them, read only when asked for, objects of other classes as inert
records, nothing the file names run, and files it cannot read named with the reason."""

import argparse
import collections
import io
import pickle
import zipfile

import jax.numpy as jnp
import numpy as np
import pytest

from wmjax.checkpoints import torch_file
from wmjax.checkpoints.torch_file import TorchFileError

pytestmark = pytest.mark.unit


def _rewrite(src, dst, edit):
  """The zip archive ``src`` copied to ``dst`` with ``edit(entries)`` applied to its
  ``{name: bytes}``."""
  with zipfile.ZipFile(src) as archive:
    entries = {name: archive.read(name) for name in archive.namelist()}
  edit(entries)
  with zipfile.ZipFile(dst, "w") as archive:
    for name, data in entries.items():
      archive.writestr(name, data)
  return dst


def _unpickle(path):
  """What ``path`` holds, its tensors unread (the archive is closed again)."""
  with torch_file.load(path) as saved:
    return saved


def test_tensors_read_as_torch_holds_them(tmp_path, torch):
  base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
  tensors = {"float32": base, "transposed": base.t(), "offset_view": base[1:, 2:4],
             "bfloat16": base.to(torch.bfloat16), "float16": base.half(),
             "int64": torch.arange(5), "bool": torch.tensor([True, False]),
             "scalar": torch.tensor(3.5), "empty": torch.zeros(0, 3)}
  torch.save({"tensors": tensors, "shared": [base, base[2]]}, tmp_path / "t.pt")
  with torch_file.load(str(tmp_path / "t.pt")) as saved:
    for name, tensor in tensors.items():
      ours = saved["tensors"][name]
      assert ours.shape == tuple(tensor.shape), name
      expected = tensor.float().numpy() if tensor.dtype == torch.bfloat16 else tensor.numpy()
      np.testing.assert_array_equal(ours.numpy().astype(expected.dtype), expected, err_msg=name)
    assert saved["tensors"]["bfloat16"].numpy().dtype == jnp.bfloat16
    assert saved["tensors"]["float16"].numpy().dtype == np.float16
    whole, row = saved["shared"]  # a view saves its whole storage, once
    assert whole.storage.entry == row.storage.entry and row.offset == 12
    np.testing.assert_array_equal(row.numpy(), base[2].numpy())


def test_only_the_tensors_asked_for_are_read(tmp_path, torch):
  """With the other state dict's storage cut out of the archive, the one asked for still reads
  and the other names the entry it lacks."""
  torch.save({"ema": {"w": torch.ones(3)}, "model": {"w": torch.zeros(3)}}, tmp_path / "a.pt")
  with torch_file.load(str(tmp_path / "a.pt")) as saved:
    entry = saved["model"]["w"].storage.entry
  _rewrite(tmp_path / "a.pt", tmp_path / "cut.pt", lambda entries: entries.pop(entry))
  with torch_file.load(str(tmp_path / "cut.pt")) as saved:
    np.testing.assert_array_equal(saved["ema"]["w"].numpy(), np.ones(3, np.float32))
    with pytest.raises(TorchFileError, match=f"the archive lacks {entry}, which a tensor names"):
      saved["model"]["w"].numpy()


class _Runs:
  """What a malicious pickle does: call a function of the reader's choosing when loaded."""

  def __init__(self, marker):
    self.marker = marker

  def __reduce__(self):
    return (open, (str(self.marker), "w"))


def test_objects_of_other_classes_are_inert_records(tmp_path, torch):
  """A module's state dict stays an OrderedDict, an optimiser's state and a config object load
  as data and records; a pickle that would open a file opens none."""
  module = torch.nn.Linear(3, 2)
  optimizer = torch.optim.AdamW(module.parameters(), lr=0.01)
  module(torch.ones(1, 3)).sum().backward()
  optimizer.step()
  torch.save({"model": module.state_dict(), "opt": optimizer.state_dict(),
              "args": argparse.Namespace(lr=0.01, dataset="rt1")}, tmp_path / "c.pt")
  with torch_file.load(str(tmp_path / "c.pt")) as saved:
    assert isinstance(saved["model"], collections.OrderedDict)
    assert list(saved["model"]) == ["weight", "bias"]
    np.testing.assert_array_equal(saved["model"]["weight"].numpy(),
                                  module.weight.detach().numpy())
    assert saved["opt"]["param_groups"][0]["lr"] == 0.01
    assert saved["opt"]["state"][0]["exp_avg"].shape == (2, 3)
    args = saved["args"]
    assert isinstance(args, torch_file.Opaque) and args.name == "argparse.Namespace"
    assert args.state == {"lr": 0.01, "dataset": "rt1"}

  marker = tmp_path / "opened"
  payload = io.BytesIO()
  pickle.dump({"ema": _Runs(marker)}, payload, protocol=2)
  _rewrite(tmp_path / "c.pt", tmp_path / "evil.pt",
           lambda entries: entries.update({"c/data.pkl": payload.getvalue()}))
  with torch_file.load(str(tmp_path / "evil.pt")) as saved:
    assert isinstance(saved["ema"], torch_file.Opaque)
    assert saved["ema"].name == f"{open.__module__}.open" and saved["ema"].args == (str(marker), "w")
  assert not marker.exists()


def test_files_it_cannot_read_say_why(tmp_path, torch):
  state = {"w": torch.arange(3, dtype=torch.float32)}
  torch.save(state, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
  with pytest.raises(TorchFileError, match=r"serialization from before 1.6.*saved again by a "
                                           r"newer PyTorch"):
    _unpickle(str(tmp_path / "legacy.pt"))
  (tmp_path / "notes.pt").write_text("not a checkpoint")
  with pytest.raises(TorchFileError, match="not a PyTorch file: torch.save writes a zip archive"):
    _unpickle(str(tmp_path / "notes.pt"))
  with pytest.raises(FileNotFoundError, match="no file at"):
    _unpickle(str(tmp_path / "missing.pt"))

  torch.save(state, tmp_path / "s.pt")
  _rewrite(tmp_path / "s.pt", tmp_path / "no_pickle.pt", lambda entries: entries.pop("s/data.pkl"))
  with pytest.raises(TorchFileError, match="with 0 data.pkl entries"):
    _unpickle(str(tmp_path / "no_pickle.pt"))
  _rewrite(tmp_path / "s.pt", tmp_path / "cut_pickle.pt",
           lambda entries: entries.update({"s/data.pkl": entries["s/data.pkl"][:20]}))
  with pytest.raises(TorchFileError, match="its data.pkl does not unpickle"):
    _unpickle(str(tmp_path / "cut_pickle.pt"))
  _rewrite(tmp_path / "s.pt", tmp_path / "short.pt",
           lambda entries: entries.update({"s/data/0": entries["s/data/0"][:8]}))
  with torch_file.load(str(tmp_path / "short.pt")) as saved:
    with pytest.raises(TorchFileError, match=r"s/data/0 holds 8 bytes, not the 3 elements"):
      saved["w"].numpy()
