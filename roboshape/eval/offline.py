"""Offline action error of a trained policy on the validation demos, split by phase: where imitation is lost.

  python -m roboshape.eval.offline WORKDIR [--train-seed S]    # writes <workdir>/eval/offline.json, prints it

Each action of each successful validation episode is predicted from the demo's own frames (teacher forcing): the
frame's window of `policy.history` frames ending at it (the first window for the first frames, as training reads
them), read at the frame's position, the mixture's mean. Its squared error (environment units, mean over the action's
dims, as bc.evaluate's `action_mse`) is averaged per phase, the phase read from the expert's own actions (the last
dim is the gripper: 1 open, -1 closed):

  approach   before the expert first closes the gripper (a push never does: all of it is approach)
  grasp      from that first close until the expert first moves up (z action > LIFT_DZ)
  lift       from there on (for place: the carry and the release too)
  first      the first FIRST_STEPS actions of an episode (also counted in approach)

and `first_move` compares the mean length of the position part of the first FIRST_STEPS actions, the expert's and
the policy's offline prediction: a policy whose first moves are near zero where the expert's are large has learnt to
continue the motion its history shows (the copycat failure of behaviour cloning with an observation history).
Needs the run's feature cache (<workdir>/features/, which the train_policy stage leaves).
"""
import argparse
import json
import os
import sys
from typing import Dict, List

import numpy as np

from roboshape import errors
from roboshape import fileio
from roboshape import rundir
from roboshape.errors import UserError
from roboshape.eval.closed_loop import FIRST_STEPS

PHASES = ("approach", "grasp", "lift", "first")
LIFT_DZ = 0.1          # a z action above this (controller units) after the close is the lift
OFFLINE_FILE = "offline.json"
BATCH = 256


def phases(actions: np.ndarray) -> Dict[str, np.ndarray]:
  """{phase: bool [T]} for an episode's expert actions [T, A] (definitions in the module docstring)."""
  t = len(actions)
  closing = np.flatnonzero(actions[:, -1] < 0)
  close = int(closing[0]) if len(closing) else t
  up = np.flatnonzero((actions[:, 2] > LIFT_DZ) & (np.arange(t) >= close))
  lift = int(up[0]) if len(up) else t
  index = np.arange(t)
  return dict(approach=index < close, grasp=(index >= close) & (index < lift), lift=index >= lift,
              first=index < FIRST_STEPS)


def windows(num_actions: int, history: int):
  """(start [T], position [T]) of the window each of an episode's T actions is predicted from."""
  t = np.arange(num_actions)
  start = np.maximum(t - history + 1, 0)
  return start, t - start


def predict(net, params, features: np.ndarray, num_actions: int, history: int) -> np.ndarray:
  """The policy's mean actions [T, A] (normalised units) for one episode's features [S, N, D]. Windows go through
  one compiled function in batches of BATCH (the last padded), so every episode reuses one compilation."""
  start, position = windows(num_actions, history)
  last = len(features) - 1
  apply = _mean_fn(net, history)
  out = []
  for i in range(0, num_actions, BATCH):
    s, p = start[i:i + BATCH], position[i:i + BATCH]
    frames = np.minimum(np.r_[s, np.repeat(s[-1:], BATCH - len(s))][:, None] + np.arange(history)[None], last)
    mean = np.asarray(apply(params, features[frames].astype(np.float32)))
    out.append(mean[np.arange(len(s)), p])
  return np.concatenate(out)


_MEAN_FNS = {}


def _mean_fn(net, history: int):
  """jit((params, tokens [BATCH, H, N, D]) -> the mixture's mean [BATCH, H, A]), one per (net, history)."""
  if (net, history) not in _MEAN_FNS:
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    from roboshape.models import heads  # pylint: disable=import-outside-toplevel
    read = jnp.broadcast_to(jnp.arange(history), (BATCH, history))
    _MEAN_FNS[(net, history)] = jax.jit(lambda params, tokens: heads.gmm_mean(net.apply(params, tokens, read)))
  return _MEAN_FNS[(net, history)]


def evaluate(workdir: str, train_seed=None) -> dict:
  """The offline figures of the policy in `workdir` (see the module docstring), as written to offline.json."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  config = rundir.load_config(workdir)
  if train_seed is None:
    train_seed = rundir.train_seeds(config)[0]
  encoder = encoders.build_encoder(config, workdir)
  feature_path = cache.feature_dir(config, workdir, encoder)
  if cache.read_manifest(feature_path) is None:
    raise UserError(f"no complete feature cache at {feature_path}: run the train_policy stage (or the cache "
                    "stage) of this run first.")
  net, params = bc.load_params(config, workdir, encoder.num_tokens, encoder.token_dim, train_seed=train_seed)
  with open(os.path.join(rundir.policy_dir(workdir, train_seed), bc.NORM_STATS_FILE)) as f:
    stats = json.load(f)
  scale, offset = np.asarray(stats["scale"], np.float32), np.asarray(stats["offset"], np.float32)
  data = cache.load_split(feature_path, "val")
  history = int(config.policy.history)
  errors_by_phase: Dict[str, List[np.ndarray]] = {p: [] for p in PHASES}
  expert_moves, policy_moves = [], []
  for e in np.flatnonzero(data["success"]):
    a, b = int(data["offsets"][e]), int(data["offsets"][e + 1])
    actions = data["action"][a:b - 1]       # the last frame holds no action
    predicted = predict(net, params, data["features"][a:b], len(actions), history) * scale + offset
    sq = np.mean((predicted - actions) ** 2, axis=-1)
    for name, where in phases(actions).items():
      errors_by_phase[name].append(sq[where])
    expert_moves.append(np.linalg.norm(actions[:FIRST_STEPS, :3], axis=-1).mean())
    policy_moves.append(np.linalg.norm(np.clip(predicted[:FIRST_STEPS, :3], -1, 1), axis=-1).mean())
  if not expert_moves:
    raise UserError(f"the cache at {feature_path} holds no successful validation episode: nothing to compare with.")
  out = {"episodes": len(expert_moves), "history": history, "train_seed": train_seed, "phases": {}}
  for name, parts in errors_by_phase.items():
    values = np.concatenate(parts)
    out["phases"][name] = dict(actions=int(len(values)),
                               action_mse=float(values.mean()) if len(values) else None)
  out["first_move"] = dict(expert=float(np.mean(expert_moves)), policy=float(np.mean(policy_moves)))
  return out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m roboshape.eval.offline", description=__doc__.split("\n")[0])
  parser.add_argument("workdir")
  parser.add_argument("--train-seed", type=int, default=None)
  args = parser.parse_args(argv)
  try:
    result = evaluate(args.workdir, args.train_seed)
  except UserError as e:
    return errors.print_error(e)
  path = os.path.join(rundir.eval_dir(args.workdir), OFFLINE_FILE)
  os.makedirs(os.path.dirname(path), exist_ok=True)
  fileio.atomic_write_json(path, result, indent=1)
  print(json.dumps(result, indent=1))
  print(f"[roboshape] wrote {path}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
