"""The config fields a stage's output was made with, recorded beside it, so that a workdir's config.json always
describes what the workdir holds.

  plan = fingerprint.check(config, workdir, redo=("train_policy",))   # before anything is written; UserError
  fingerprint.apply(plan, workdir)                                    # sets aside what --redo names, once held
  fingerprint.record(config, workdir, "train_policy")                 # as the stage starts

Why: a stage that finds its output finished skips, and one that finds it part-done resumes, while the run rewrites
config.json with whatever the command line says. A field the stage read that leaves the parameters' shapes as they
were (a learning rate, a batch size, a seed, the history length) then leaves a config.json that did not make what
the workdir holds. So each stage whose output depends on such fields records them (`READS`, less `NOT_READ`) in
<stage folder>/fingerprint.json (rundir.fingerprint_path) as it starts, and `check` compares a rerun's config with
every record, whether or not the rerun runs that stage, before config.json is written. A difference stops the run
in one line naming the stages, the fields and their two values, and the two ways forward: another --workdir, or
`--redo=STAGE` (launch.py), which sets that stage's output aside under a name that says what it was made with
(`aside_name`) and runs the stage again. `--redo` of a stage whose record agrees with the config does nothing:
the same command, with it, resumes after a kill.

Recorded stages (`RECORDED`) and their folders (`outputs`, what `--redo` sets aside):
  collect       the dataset in the run's own data folder: its roboshape.json already records what it was made
                with (roboshape/data/collect.py, `config_summary`); its differences come from there.
  pretrain      <workdir>/<encoder>/ (and <workdir>/features/, whose caches name the encoder by its checkpoint
                folder and step, which a pretraining run again gives anew).
  train_policy  <workdir>/policy/ (and eval/, report/: the evaluation of that policy).
The cache needs no record of its own (its folder's name hashes the encoder's identity, the dataset and the dtype:
roboshape/train/cache.py), nor does the evaluation (its log names the policy's checkpoints and control settings:
roboshape/eval/closed_loop.py, policy_fingerprint).

Not differences (`NOT_READ`): how long (the steps: more steps resume), how often (logging, checkpoints,
validation), where (data.dir, pretrain.from_workdir), with which workers, which training seeds run (each seed's run
is trained alike), and what only validation or control reads. A field a record lacks (one added to the configs
since) compares as the value the stage ran with before it existed (rundir.ADDED). A workdir written before stages
recorded fingerprints is read with its config.json as the
record of every stage that holds output, said once, when that record is written beside the output.
"""
import dataclasses
import json
import os
import re
from typing import Any, Dict, List, Optional, Sequence, Tuple

from roboshape import encoders
from roboshape import fileio
from roboshape import rundir
from roboshape.errors import UserError

RECORDED = ("collect", "pretrain", "train_policy")     # the stages --redo takes, in the order a run takes them
# The dataset: what every later stage is made from.
_DATASET = ("task", "env", "data")
# Fields (dotted prefixes) that are never a difference: see the module's docstring.
NOT_READ = (
    "env.sim_backend", "data.dir",
    "pretrain.train.steps", "pretrain.train.checkpoint_every", "pretrain.train.keep_checkpoints",
    "pretrain.train.log_every", "pretrain.eval", "pretrain.from_workdir", "pretrain.train_seeds", "savi.eval",
    "policy.train.steps", "policy.train.log_every", "policy.train.eval_every", "policy.train.checkpoint_every",
    "policy.train.val_batch_size", "policy.train.max_val_samples", "policy.train_seeds", "policy.eval",
)

Difference = Tuple[str, Any, Any]      # (dotted field, the recorded value, this config's)


def reads(config, stage: str) -> Tuple[str, ...]:
  """The config fields (dotted prefixes) the output of `stage` ("pretrain", "train_policy") depends on: its own
  and those of the stages it is made from. The encoder's own sections and fields (encoders.Kind.sections), and
  config.seed where no training seeds are given (with them each seed's run trains with its seed)."""
  sections = tuple(encoders.get(config.encoder).sections)
  pretraining = _DATASET + ("encoder",) + sections
  pretrain_seed = () if tuple(config.pretrain.train_seeds) else ("seed",)
  if stage == "pretrain":
    return pretraining + pretrain_seed
  policy_seed = () if tuple(config.policy.train_seeds) else ("seed",)
  return pretraining + ("policy",) + tuple(dict.fromkeys(pretrain_seed + policy_seed))


def _flat(tree, prefix: str = "") -> Dict[str, Any]:
  out = {}
  for key, value in tree.items():
    if isinstance(value, dict):
      out.update(_flat(value, f"{prefix}{key}."))
    else:
      out[f"{prefix}{key}"] = value
  return out


def _under(field: str, prefixes: Sequence[str]) -> bool:
  return any(field == p or field.startswith(p + ".") for p in prefixes)


def fingerprint(config, stage: str) -> Dict[str, Any]:
  """{dotted field: value} of every field `stage` reads (`reads`, less `NOT_READ`), as JSON data."""
  tree = json.loads(config.to_json_best_effort())
  wanted = reads(config, stage)
  return {k: v for k, v in sorted(_flat(tree).items()) if _under(k, wanted) and not _under(k, NOT_READ)}


def stage_dir(config, workdir: str, stage: str) -> Optional[str]:
  """The folder whose fingerprint.json records `stage`: the pretrained encoder's (None for an encoder without a
  pretrain stage, or one served from another workdir) or the policy's."""
  if stage == "train_policy":
    return rundir.policy_dir(workdir)
  if stage == "pretrain" and encoders.get(config.encoder).pretrain and not config.pretrain.get("from_workdir"):
    return rundir.pretrain_dir(workdir, config.encoder)
  return None


def outputs(config, workdir: str, stage: str) -> List[str]:
  """What `--redo=stage` sets aside, where it exists: the stage's folders (see the module's docstring)."""
  if stage == "collect":
    paths = [] if config.data.dir else [rundir.data_root(config, workdir)]
  elif stage == "pretrain":
    paths = [rundir.pretrain_dir(workdir, config.encoder), rundir.features_root(workdir)]
  else:
    paths = [rundir.policy_dir(workdir), rundir.eval_dir(workdir), rundir.report_dir(workdir)]
  return [p for p in paths if os.path.exists(p)]


def _holds_output(folder: str) -> bool:
  """Whether `folder` holds anything besides its fingerprint: what a stage wrote."""
  return os.path.isdir(folder) and any(n != rundir.FINGERPRINT_FILE for n in os.listdir(folder))


def recorded(config, workdir: str, stage: str) -> Tuple[Optional[Dict[str, Any]], bool]:
  """(the fields the output of `stage` in `workdir` was made with, whether they are taken from config.json): its
  fingerprint.json; for output written before fingerprints were recorded, the workdir's config.json (the config
  the last run wrote there, the best record there is); (None, False) when the stage holds no output."""
  folder = stage_dir(config, workdir, stage)
  if folder is None or not _holds_output(folder):
    return None, False
  path = rundir.fingerprint_path(folder)
  if os.path.exists(path):
    try:
      with open(path, encoding="utf-8") as f:
        return _with_added(dict(json.load(f)["fields"]), config, stage), False
    except (OSError, ValueError, KeyError, TypeError) as e:
      raise UserError(f"{path} is damaged ({type(e).__name__}: {e}): it records the config fields the {stage} "
                      f"stage's output beside it was made with; restore it, or run with --redo={stage} to set that "
                      "output aside and make it again.") from None
  if not os.path.exists(rundir.config_path(workdir)):
    return None, False
  return fingerprint(rundir.load_config(workdir), stage), True


def _with_added(record: Dict[str, Any], config, stage: str) -> Dict[str, Any]:
  """A fingerprint record with each field the stage reads that was added to the configs after it was written
  (rundir.ADDED) at the value the stage ran with then."""
  wanted = reads(config, stage)
  return {**{f: json.loads(json.dumps(v)) for f, v in rundir.ADDED.items()
             if f not in record and _under(f, wanted) and not _under(f, NOT_READ)}, **record}


def differences(old: Dict[str, Any], new: Dict[str, Any]) -> List[Difference]:
  """[(field, old value, new value)] over the fields both records hold (a field one lacks is not compared)."""
  return [(k, old[k], new[k]) for k in new if k in old and old[k] != new[k]]


@dataclasses.dataclass
class Plan:
  """What a run does to a workdir's recorded stages before it writes config.json: `set_aside` {stage: (its
  differences, the folders to set aside)}, for the stages --redo names whose output differs; `adopt` {stage: the
  fields taken from config.json}, for output written before fingerprints, recorded beside it (`apply`)."""
  set_aside: Dict[str, Tuple[List[Difference], List[str]]] = dataclasses.field(default_factory=dict)
  adopt: Dict[str, Dict[str, Any]] = dataclasses.field(default_factory=dict)


def check(config, workdir: str, redo: Sequence[str] = (), dataset: Sequence[Difference] = ()) -> Plan:
  """The `Plan` for running `config` on `workdir`, or a one-line UserError, before anything is touched, when a
  recorded stage's output was made with other values of the fields it reads and --redo does not name it.

  `dataset`: the differences of the dataset in the run's own data folder (collect.own_dataset_differences), the
  collect stage's record.
  """
  plan, found = Plan(), {}
  if dataset:
    found["collect"] = list(dataset)
  for stage in RECORDED[1:]:
    old, from_config = recorded(config, workdir, stage)
    if old is None:
      continue
    diff = differences(old, fingerprint(config, stage))
    if diff:
      found[stage] = diff
    elif from_config:
      plan.adopt[stage] = old
  refused = [s for s in found if s not in redo]
  if refused:
    raise UserError(_refusal(config, workdir, found))
  for stage, diff in found.items():
    plan.set_aside[stage] = (diff, outputs(config, workdir, stage))
  return plan


def _refusal(config, workdir: str, found: Dict[str, List[Difference]]) -> str:
  """The one line that refuses a rerun whose config differs from what the stages `found` made."""
  fields = {}
  for diff in found.values():
    for field, old, new in diff:
      fields.setdefault(field, (old, new))
  said = "; ".join(f"{field}: {old!r} there, {new!r} in this config" for field, (old, new) in fields.items())
  stages = list(found)
  names = " and ".join(f"the {s} stage" for s in stages)
  moves = [f"{p} as {os.path.basename(aside_name(p, found[s]))}" for s in stages for p in outputs(config, workdir, s)]
  aside = f" (setting aside {', '.join(moves)})" if moves else ""
  return (f"{workdir} holds what {names} made with other settings ({said}), and its config.json must describe "
          f"what it holds: use another --workdir, or run again with --redo={','.join(stages)} to run "
          f"{'them' if len(stages) > 1 else 'it'} again{aside}. Nothing was changed.")


def aside_name(path: str, diff: Sequence[Difference]) -> str:
  """Where `--redo` moves `path`: beside it, named after what it was made with, e.g.
  policy.with-learning_rate=1000000.0 (the first two fields that differ, +N for more; .2, .3, ... when taken)."""
  parts = [f"{field.rsplit('.', 1)[-1]}={_word(old)}" for field, old, _ in diff[:2]]
  if len(diff) > 2:
    parts.append(f"+{len(diff) - 2}")
  base = f"{path.rstrip(os.sep)}.with-{','.join(parts)}"
  name, n = base, 1
  while os.path.exists(name):
    n += 1
    name = f"{base}.{n}"
  return name


def _word(value) -> str:
  text = json.dumps(value) if not isinstance(value, str) else value
  return re.sub(r"[^A-Za-z0-9._+-]+", "_", text).strip("_")[:40] or "_"


def apply(plan: Plan, workdir: str, config) -> None:
  """Carries out `plan` (the run holds the workdir): moves each folder of `set_aside` to its `aside_name`, and
  writes the fingerprint of each stage of `adopt`, saying once that it was taken from config.json."""
  for stage, (diff, paths) in plan.set_aside.items():
    for path in paths:
      target = aside_name(path, diff)
      os.replace(path, target)
      print(f"[roboshape] --redo={stage}: set aside {path} as {target}", flush=True)
  for stage, fields in plan.adopt.items():
    folder = stage_dir(config, workdir, stage)
    _write(folder, stage, fields)
    print(f"[roboshape] {folder} was written before stages recorded the config fields they read: its "
          f"config.json is taken as the record of the {stage} stage, now in {rundir.fingerprint_path(folder)}",
          flush=True)


def record(config, workdir: str, stage: str) -> None:
  """Writes the fields `stage` reads, as `config` sets them, into its folder's fingerprint.json (nothing for a
  stage that records none here), before the stage writes anything there."""
  folder = stage_dir(config, workdir, stage) if stage in RECORDED[1:] else None
  if folder is not None:
    _write(folder, stage, fingerprint(config, stage))


def _write(folder: str, stage: str, fields: Dict[str, Any]) -> None:
  os.makedirs(folder, exist_ok=True)
  fileio.atomic_write_json(rundir.fingerprint_path(folder), {
      "stage": stage, "fields": fields,
      "about": "the config fields this stage's output was made with (roboshape/train/fingerprint.py)"}, indent=1)
