"""Official torch checkpoints -> Flax variables, shared by the R3M and DINO baselines.

Torch is used here only to unpickle the file; every tensor leaves as a numpy array. The Flax modules of
roboshape/baselines name their submodules after the torch ones, with a numbered child joined to its parent by "_"
(torch `layer1.0.downsample.1.running_var` <-> Flax `batch_stats/layer1_0/downsample_1/var`), so one rule maps
every Flax leaf to its torch key and layout:

  conv kernel  [kh, kw, in, out]  <-  weight [out, in, kh, kw]
  dense kernel [in, out]          <-  weight [out, in]
  norm scale   [C]                <-  weight [C]
  bias, cls_token, pos_embed      <-  same name, same layout
  batch_stats mean / var          <-  running_mean / running_var
"""
import hashlib
import os
import pickle
from typing import Any, Dict, Iterable, Mapping, Tuple

from absl import logging
import jax
import numpy as np

from roboshape.errors import UserError

_LEAF_TO_TORCH = {"scale": "weight", "mean": "running_mean", "var": "running_var"}
_IGNORED_SUFFIXES = ("num_batches_tracked",)


def check_file(path: str, *, what: str, download: str) -> None:
  """Raises UserError, saying where to get the file, when `path` is not a file (a check that reads nothing)."""
  if not os.path.isfile(path):
    raise UserError(f"{what} weights not found at {path}; download the official file from {download} and put it "
                    "there (or point the config's path field to it). roboshape never downloads weights.")


def load_state(path: str, *, what: str, download: str) -> Dict[str, Any]:
  """Unpickles a torch checkpoint file into a dict; tensors stay torch tensors (see `to_numpy`).

  Args:
    path: the file.
    what: the model's name for messages, e.g. "R3M ResNet-50".
    download: where a user gets the file (a URL), for the missing-file message.

  Raises:
    UserError: the file is missing or is not a torch checkpoint holding a dict.
  """
  check_file(path, what=what, download=download)
  import torch  # pylint: disable=import-outside-toplevel
  try:
    try:
      state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
      if "Unsupported global" not in str(e):
        raise
      # A checkpoint that pickles Python objects besides tensors (e.g. training arguments) needs the full
      # unpickler; the user chose this file as the official one.
      logging.warning("%s holds Python objects besides tensors; loading it with weights_only=False.", path)
      state = torch.load(path, map_location="cpu", weights_only=False)
  except Exception as e:  # pylint: disable=broad-except
    text = str(e).split("WeightsUnpickler error:")[-1]
    reason = ([line.strip() for line in text.splitlines() if line.strip()] or [type(e).__name__])[0]
    raise UserError(f"cannot read {path} as a torch checkpoint of {what}: {reason}") from None
  if not isinstance(state, Mapping):
    raise UserError(f"{path} holds a {type(state).__name__}, not the state_dict of {what}")
  return dict(state)


def to_numpy(state: Mapping[str, Any], prefix: str = "") -> Dict[str, np.ndarray]:
  """The tensors of `state` whose keys start with `prefix`, keyed without it, as float32 numpy arrays."""
  out = {}
  for key, value in state.items():
    if isinstance(key, str) and key.startswith(prefix) and hasattr(value, "detach"):
      out[key[len(prefix):]] = value.detach().cpu().float().numpy()
  return out


def file_identity(path: str, arch: str, *extra: str, head_bytes: int = 8 << 20) -> str:
  """`path|sha256 of the first 8 MB and the size|arch|extra...`, which changes whenever the weights change."""
  digest = hashlib.sha256()
  with open(path, "rb") as f:
    digest.update(f.read(head_bytes))
  digest.update(str(os.path.getsize(path)).encode())
  return "|".join([os.path.abspath(path), digest.hexdigest()[:16], arch, *extra])


def _torch_key(path: Tuple[str, ...]) -> str:
  """Flax leaf path (without the collection) -> torch state_dict key."""
  *modules, leaf = path
  parts = []
  for name in modules:
    head, _, tail = name.rpartition("_")
    parts.extend([head, tail] if head and tail.isdigit() else [name])
  return ".".join(parts + [_LEAF_TO_TORCH.get(leaf, "weight" if leaf == "kernel" else leaf)])


def _torch_layout(leaf: str, flax_shape: Tuple[int, ...]) -> Tuple[int, ...]:
  if leaf == "kernel" and len(flax_shape) == 4:
    h, w, i, o = flax_shape
    return (o, i, h, w)
  if leaf == "kernel" and len(flax_shape) == 2:
    return tuple(reversed(flax_shape))
  return tuple(flax_shape)


def _to_flax_layout(array: np.ndarray, leaf: str) -> np.ndarray:
  if leaf == "kernel" and array.ndim == 4:
    return np.transpose(array, (2, 3, 1, 0))
  if leaf == "kernel" and array.ndim == 2:
    return array.T
  return array


def expected_torch_shapes(template: Mapping[str, Any]) -> Dict[str, Tuple[int, ...]]:
  """torch key -> torch shape for every leaf of a Flax variables template (e.g. from `jax.eval_shape`)."""
  shapes = {}
  for tree in template.values():
    for path, leaf in _flat(tree):
      shapes[_torch_key(path)] = _torch_layout(path[-1], tuple(leaf.shape))
  return shapes


def _flat(tree, prefix=()) -> Iterable[Tuple[Tuple[str, ...], Any]]:
  for key, value in tree.items():
    if isinstance(value, Mapping):
      yield from _flat(value, prefix + (key,))
    else:
      yield prefix + (key,), value


def _set(tree: Dict[str, Any], path: Tuple[str, ...], value) -> None:
  for key in path[:-1]:
    tree = tree.setdefault(key, {})
  tree[path[-1]] = value


def check_keys(tensors: Mapping[str, np.ndarray], template: Mapping[str, Any], *, path: str, what: str,
               ignore: Tuple[str, ...] = ()) -> None:
  """Raises UserError listing the mismatching keys when `tensors` are not the weights `template` expects."""
  expected = expected_torch_shapes(template)
  present = {k: tuple(v.shape) for k, v in tensors.items()
             if not k.endswith(_IGNORED_SUFFIXES) and not k.startswith(ignore)}
  missing = sorted(set(expected) - set(present))
  unexpected = sorted(set(present) - set(expected))
  wrong = sorted(f"{k} {present[k]} (expected {expected[k]})"
                 for k in set(expected) & set(present) if present[k] != expected[k])
  if missing or unexpected or wrong:
    def few(keys):
      return ", ".join(keys[:5]) + (f" (+{len(keys) - 5} more)" if len(keys) > 5 else "")
    problems = [f"{len(missing)} missing: {few(missing)}" if missing else "",
                f"{len(wrong)} of another shape: {few(wrong)}" if wrong else "",
                f"{len(unexpected)} unexpected: {few(unexpected)}" if unexpected else ""]
    raise UserError(f"{path} is not the {what} checkpoint (keys of another model): "
                    + "; ".join(p for p in problems if p))


def to_flax(tensors: Mapping[str, np.ndarray], template: Mapping[str, Any]) -> Dict[str, Any]:
  """Fills a Flax variables `template` ({collection: tree of shapes}) from torch tensors (checked by `check_keys`)."""
  variables = {}
  for collection, tree in template.items():
    out = {}
    for path, leaf in _flat(tree):
      array = _to_flax_layout(np.asarray(tensors[_torch_key(path)], np.float32), path[-1])
      assert array.shape == tuple(leaf.shape), (path, array.shape, leaf.shape)
      _set(out, path, array)
    variables[collection] = out
  return jax.tree.map(jax.numpy.asarray, variables)
