"""A run workdir with randomly initialised encoder and policy weights, for speed measurements and rollout tests.

  untrained.write_run(config, workdir)        # any registered encoder; one without a pretrain stage as it is
  policy = roboshape.train.bc.load_policy(workdir)

Writes exactly what the pretrain and train_policy stages leave behind (config.json, the pretrained encoder's
<encoder>/checkpoints when it has a pretrain stage, policy/checkpoints, policy/norm_stats.json with identity
normalisation), so the real loading path, the real `Policy` and SAVi's slot videos run on it; only the weights
are untrained. Speed does not depend on them.
"""
import json
import os

import jax
import numpy as np


def write_run(config, workdir: str, seed: int = 0) -> str:
  """Writes the untrained encoder + policy run of `config` into `workdir`; returns `workdir`."""
  # pylint: disable=import-outside-toplevel
  from roboshape import encoders
  from roboshape import rundir
  from roboshape.checkpoint import Checkpointer
  from roboshape.models import policy as policy_lib
  from roboshape.train import bc
  from roboshape.train import pretrain
  config = config.copy_and_resolve_references()
  config.pretrain.train_seeds = ()      # one model, in <encoder>/checkpoints: no seed to select among
  rundir.save_config(config, workdir)
  if encoders.get(config.encoder).model is not None:
    comp = pretrain.compiled(config)
    r = config.env.resolution
    # Jitted inits (one compilation each) are faster than op-by-op ones; a one-frame clip has the same params.
    encoder_state = jax.jit(lambda key: comp.init_state(key, (1, 1, r, r, 3)))(jax.random.key(seed))
    with Checkpointer(rundir.checkpoints(rundir.pretrain_dir(workdir, config.encoder))) as ckpt:
      ckpt.save(0, encoder_state)
  encoder = encoders.build_encoder(config, workdir)
  net = policy_lib.net_from_config(config.policy)
  optimizer = bc.make_optimizer(config.policy.train)
  state = jax.jit(lambda: bc.init_state(net, optimizer, (1, 1, encoder.num_tokens, encoder.token_dim), seed))()
  with Checkpointer(rundir.checkpoints(rundir.policy_dir(workdir))) as ckpt:
    ckpt.save(0, state)
  dim = config.policy.action_dim
  with open(os.path.join(rundir.policy_dir(workdir), bc.NORM_STATS_FILE), "w") as f:
    json.dump(dict(scale=np.ones(dim).tolist(), offset=np.zeros(dim).tolist()), f)
  return workdir
