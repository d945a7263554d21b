"""Checkpoints travel between device counts: a policy and a SAVi trained over two (host) devices, as launch.py trains
on a 2-core CPU, load and evaluate in a one-device process (a notebook's JAX), resume there, and resume over two
devices again from what the one-device process saved. Each phase is a subprocess with its own device count."""
import os
import subprocess
import sys

from test_reliability import features_run

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# One phase of the journey: argv = phase, devices, policy workdir, its feature cache, SAVi workdir, policy steps, SAVi
# steps, results.
# A phase checks that the parameters it restores equal those the previous phase saved (results/<phase>.npz, the
# live train state at its last step), that training resumes at the saved step (the steps the train steps are called
# at), and, on one device, that the restored policy acts and gives the saving process's validation NLL and that the
# restored SAVi encodes; then it saves its own last parameters for the next phase.
_PHASE = r'''
import json, os, sys
import jax, numpy as np
jax.config.update("jax_disable_most_optimizations", True)     # compile-bound: XLA's cheap optimisation level
phase, devices, policy_dir, features, savi_dir, policy_steps, savi_steps, results = sys.argv[1:]
assert jax.local_device_count() == int(devices), jax.devices()
import jax.numpy as jnp
from configs import common
from roboshape import encoders, rundir
from roboshape.checkpoint import Checkpointer
from roboshape.encoders import savi as savi_encoder
from roboshape.models.encoder import FrozenEncoder
from roboshape.train import bc, cache, pretrain

RES, K, D = 8, 2, 4
w = jax.random.normal(jax.random.PRNGKey(3), (RES * RES * 3, K * D)) / 16.0   # tests/test_reliability.py's toy
def toy_step(params, state, frames):
  x = frames.reshape(frames.shape[0], -1).astype(jnp.float32) / 255.0
  return jnp.tanh(x @ params["w"]).reshape(-1, K, D), state
toy = FrozenEncoder(name="toy", params={"w": w}, step=toy_step, init_state=lambda b: (), num_tokens=K, token_dim=D,
                    identity="toy-v1")
encoders.build_encoder = lambda config, workdir: toy

previous = {"train": None, "one": "train", "two": "one"}[phase]
def saved(name):
  with np.load(os.path.join(results, f"{previous}_{name}.npz")) as f:
    return [f[f"a{i}"] for i in range(len(f.files))]
def save(name, tree):
  np.savez(os.path.join(results, f"{phase}_{name}.npz"),
           **{f"a{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(tree))})
def same(tree, arrays):
  leaves = jax.tree.leaves(tree)
  assert len(leaves) == len(arrays) and all(np.array_equal(np.asarray(a), b) for a, b in zip(leaves, arrays))

# The policy, trained by bc.train (the train_policy stage) on the cached toy features.
config = rundir.load_config(policy_dir)
config.policy.train.steps = int(policy_steps)
if previous:
  same(bc.load_params(config, policy_dir, K, D)[1], saved("policy"))
  with Checkpointer(rundir.checkpoints(rundir.policy_dir(policy_dir))) as ckpt:
    assert ckpt.restores(ckpt.latest_step())                       # the stage's "already trained?" check
if phase == "one":                                                 # evaluate where it was not trained
  policy = bc.load_policy(policy_dir)
  policy.reset()
  frames = np.random.default_rng(0).integers(0, 255, (3, RES, RES, 3), dtype=np.uint8)
  actions = np.stack([policy.act(f) for f in frames])
  assert actions.shape == (3, 7) and np.isfinite(actions).all()
  with open(os.path.join(results, "train_summary.json")) as f:
    summary = json.load(f)
  net, params = bc.load_params(config, policy_dir, K, D)
  with open(os.path.join(policy_dir, "policy", "norm_stats.json")) as f:
    stats = json.load(f)
  pc = config.policy
  windows = bc.Windows(cache.load_split(features, "val"), pc.history, (stats["scale"], stats["offset"]))
  val = bc.evaluate(bc.make_eval_step(net), params, windows, pc.train.val_batch_size, pc.train.max_val_samples,
                    stats["scale"])
  np.testing.assert_allclose(val["nll"], summary["val_nll"], rtol=1e-5)
calls, last, make = [], {}, bc.make_train_step
def counting(net, optimizer):
  step = make(net, optimizer)
  def counted(state, batch, rng):
    calls.append(int(state["step"]))
    last["state"], metrics = step(state, batch, rng)
    return last["state"], metrics
  return counted
bc.make_train_step = counting
summary = bc.train(config, policy_dir, features)
start = {"train": 0, "one": 10, "two": 20}[phase]
assert calls == list(range(start, int(policy_steps))), calls       # resumed at the saved step
assert summary["step"] == int(policy_steps)
save("policy", last["state"]["params"])
if phase == "train":
  with open(os.path.join(results, "train_summary.json"), "w") as f:
    json.dump(summary, f)

# SAVi, pretrained by pretrain.train (the pretrain stage) on one fixed clip.
clip = np.random.default_rng(1).integers(0, 255, (6, 16, 16, 3), dtype=np.uint8)
if phase == "train":
  sc = common.get_config("push", "savi", "tiny")
  sc.env.resolution = 16
  s = sc.savi
  s.num_slots, s.slot_size, s.slot_mlp_size = 2, 8, 16
  s.num_iterations, s.encoder.features, s.encoder.strides, s.encoder.kernel_size = 1, (8, 8), (1, 1), 3
  s.encoder.mlp_size, s.encoder.output_size = 8, 8
  s.predictor.num_heads, s.predictor.mlp_size = 2, 16
  s.decoder.features, s.decoder.strides, s.decoder.kernel_size = (8, 8), (2, 1), 3
  t = sc.pretrain.train
  t.batch_size, t.clip_length, t.warmup_steps = 2, 6, 1      # 2: split over two devices
  t.checkpoint_every, t.keep_checkpoints = 2, 2
  rundir.save_config(sc, savi_dir)
sc = rundir.load_config(savi_dir)
sc.pretrain.train.steps = int(savi_steps)
if previous:
  model, params, step = savi_encoder.load(savi_dir)
  same(params, saved("savi"))
  if phase == "one":
    tokens = savi_encoder.load_encoder(savi_dir).encode_episode(clip)
    assert tokens.shape == (6, 2, 8) and np.isfinite(np.asarray(tokens)).all()
starts = []
def batches_from(first):
  starts.append(first)
  while True:
    yield {"video": np.stack([clip, clip]), "episode_seed": np.array([1, 2])}
result = pretrain.train(sc, savi_dir, batches_from)
assert starts == [{"train": 0, "one": 2, "two": 4}[phase]] and result["step"] == int(savi_steps), starts
assert pretrain.compiled(sc).dp.num_devices == int(devices)
save("savi", result["params"])
print("phase", phase, "ok")
'''


def _phase(phase, devices, policy_dir, features, savi_dir, policy_steps, savi_steps, results):
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
  env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=flags.strip(), PYTHONPATH=ROOT)
  out = subprocess.run([sys.executable, "-c", _PHASE, phase, str(devices), policy_dir, features, savi_dir,
                        str(policy_steps), str(savi_steps), results], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=600, check=False)
  assert out.returncode == 0 and f"phase {phase} ok" in out.stdout, out.stderr[-4000:]
  assert "does not restore" not in out.stderr and "damaged" not in out.stderr, out.stderr[-4000:]


def test_a_policy_and_a_savi_trained_on_two_devices_load_evaluate_and_resume_on_one_and_back(tmp_path):
  workdir = str(tmp_path / "run")
  os.makedirs(workdir)
  _, features = features_run(workdir)                       # cached toy features: a policy to train from scratch
  savi_dir, results = str(tmp_path / "savi_run"), str(tmp_path / "results")
  os.makedirs(results)
  _phase("train", 2, workdir, features, savi_dir, 10, 2, results)   # over two devices, as launch.py on 2 cores
  _phase("one", 1, workdir, features, savi_dir, 20, 4, results)     # loaded, evaluated and resumed on one device
  _phase("two", 2, workdir, features, savi_dir, 30, 6, results)     # and resumed over two devices again
  for directory in (os.path.join(workdir, "policy", "checkpoints"), os.path.join(savi_dir, "savi", "checkpoints")):
    assert not [n for n in os.listdir(directory) if n.startswith("damaged")]
