"""The numpy bridge to the simulator: EnvSpec, SimPool and SimWorkerError.

Importing this package never imports sapien or mani_skill; workers are separate processes (roboshape/sim/worker.py).
What crosses the bridge is numpy arrays and python scalars, in two dicts:

  episode dict (SimPool.collect; a worker's `collect seed`): one oracle-expert episode of T steps:
    task, level, seed, env_version, success, terminated; image uint8 [T+1, H, W, 3], segmentation uint8
    [T+1, H, W], state float32 [T+1, envs.state.DIM] (the privileged state), depth uint16 [T+1, H, W] in
    millimetres (when the spec asks for depth), action float32 [T, 7], reward float32 [T].
  frame dict (SimPool.reset and SimPool.step, batched over the pool's N envs): image uint8 [N, H, W, 3],
    segmentation, state, [depth,] success bool [N], done bool [N], elapsed int32 [N], reached bool [N, M] (the
    task's milestones reached since the reset, named by pool.milestones = roboshape.envs.MILESTONES[task]).
"""
from roboshape.sim.pool import SimPool, SimWorkerError
from roboshape.sim.spec import CAMERA_KEYS, EnvSpec, check_seeds

__all__ = ["CAMERA_KEYS", "EnvSpec", "SimPool", "SimWorkerError", "check_seeds"]
