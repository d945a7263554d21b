"""A simulator worker: a fresh python process that owns one RoboShape env and speaks numpy over a socket.

Started by SimPool as `python -m roboshape.sim.worker FD SPEC_JSON` (never by importing the parent's modules, so it
never imports TensorFlow or JAX). Requests are (command, argument) tuples; replies are ("ok", payload) or
("error", one-line message). Payloads are numpy arrays and python scalars only.

Commands:
  collect seed    -> the episode dict of roboshape/sim/__init__.py (the oracle expert run from `seed`, with the
                     privileged state; with depth when the spec asks for depth; every camera of the spec's
                     `cameras` under its keys, roboshape/envs/camera.py: image, wrist_image, ...)
  reset (seed, render) -> one env's frame dict (each camera's image, segmentation [and depth], state, success, done, elapsed,
                     reached: bool [M], the task's milestones reached so far, roboshape.envs.MILESTONES);
                     with render False the camera is not rendered until the next reset: image, segmentation (and
                     depth) are zeros, the state is real (a step then costs the physics alone, several times
                     less than a rendered one on a CPU renderer)
  step action     -> frame dict after executing `action` float32 [7] (a no-op once the episode is done)
  close           -> exits
"""
import gc
import json
import os
import sys
import traceback


def _one_line(e: BaseException) -> str:
  text = str(e).strip().splitlines()
  return f"{type(e).__name__}: {text[0] if text else ''}"


class Worker:
  """One env + its expert; every method returns plain numpy / python values."""

  def __init__(self, spec: dict):
    import numpy as np  # pylint: disable=import-outside-toplevel
    import torch  # pylint: disable=import-outside-toplevel
    torch.set_num_threads(1)
    import mani_skill  # pylint: disable=import-outside-toplevel
    from roboshape import envs  # pylint: disable=import-outside-toplevel
    from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
    from roboshape.envs import experts  # pylint: disable=import-outside-toplevel
    self.np, self.torch = np, torch
    self.cameras = camera.check(spec.get("cameras", camera.DEFAULT))
    self.keys = {name: camera.keys(name) for name in self.cameras}       # image, segmentation, depth keys
    backend = {"cpu": "physx_cpu", "gpu": "physx_cuda"}.get(spec["sim_backend"], spec["sim_backend"])
    self.env = envs.make_env(spec["task"], spec["level"], resolution=spec["resolution"],
                             min_distractors=spec["min_distractors"], max_distractors=spec["max_distractors"],
                             sim_backend=backend, cameras=self.cameras,
                             obs_mode="rgb+depth+segmentation" if spec.get("depth") else "rgb+segmentation")
    self.task = self.env.unwrapped
    self.obs_mode = self.task.obs_mode
    self.spec = spec
    self.horizon = spec["max_episode_steps"] or self.task.HORIZON
    self.expert = experts.make_expert(spec["task"], self.task.num_envs, self.task.device)
    self.env_version = f"{envs.ENV_VERSION}+mani_skill-{mani_skill.__version__}"
    self._frame = self._state = self._start = None
    self.reached = np.zeros(len(envs.MILESTONES[spec["task"]]), bool)
    self.elapsed, self.success, self.done = 0, False, True
    # Every reset rebuilds the scene, and ManiSkill then runs gc.collect(), which scans every object of this process:
    # most of a reset's time. Freezing what start-up built (modules, the env) leaves it out of those scans.
    gc.freeze()

  def info(self) -> dict:
    return dict(horizon=self.horizon, env_version=self.env_version, pid=os.getpid())

  def _observe(self, obs) -> dict:
    """Every camera's frames {image: uint8 [H, W, 3], segmentation: uint8 [H, W], (depth: uint16 [H, W]), and the
    other cameras' under their keys}: zeros when the episode is not rendered."""
    np, r, depth = self.np, self.spec["resolution"], bool(self.spec.get("depth"))
    self._state = self.task.state_vector()[0]
    views = {}
    for name, (image, segmentation, depth_key) in self.keys.items():
      if "sensor_data" not in obs:  # not rendering this episode (reset with render False)
        views[image], views[segmentation] = np.zeros((r, r, 3), np.uint8), np.zeros((r, r), np.uint8)
        if depth:
          views[depth_key] = np.zeros((r, r), np.uint16)
        continue
      rgb, seg = self.task.frames(obs, name)
      views[image], views[segmentation] = rgb[0], seg[0]
      if depth:
        views[depth_key] = self.task.depth(obs, name)[0]
    return views

  def _reset(self, seed: int, render: bool = True):
    # ManiSkill captures the cameras in get_obs() unless the obs mode is a state one; switching the mode per
    # episode skips the rendering and leaves the cameras in the scene for the next rendered episode.
    self.task._obs_mode = self.obs_mode if render else "state_dict"  # pylint: disable=protected-access
    obs, _ = self.env.reset(seed=int(seed))
    self.expert.reset()
    self.elapsed, self.success, self.done = 0, False, False
    self._start = self.task.cube.pose.p.clone()
    self.reached[:] = False
    return self._observe(obs)

  def _step(self, action):
    obs, reward, _, _, info = self.env.step(self.torch.as_tensor(action[None], dtype=self.torch.float32))
    self.elapsed += 1
    self.reached |= self.task.milestones(self._start, info)[0].cpu().numpy().astype(bool)
    self.success = bool(info["success"][0])
    self.done = self.success or self.elapsed >= self.horizon
    return self._observe(obs), float(reward[0])

  def _frame_dict(self, views: dict) -> dict:
    self._frame = (views, self._state)
    return self._last_frame()

  def _last_frame(self) -> dict:
    views, state = self._frame
    return dict(views, state=state, success=self.success, done=self.done, elapsed=self.elapsed,
                reached=self.reached.copy())

  def reset(self, arg) -> dict:
    """arg: (seed, render), or a seed alone (rendered)."""
    seed, render = arg if isinstance(arg, (tuple, list)) else (arg, True)
    return self._frame_dict(self._reset(seed, bool(render)))

  def step(self, action) -> dict:
    np = self.np
    action = np.clip(np.asarray(action, np.float32).reshape(7), -1.0, 1.0)
    if self.done:
      if self._frame is None:
        raise RuntimeError("step before reset: call pool.reset(seeds) first")
      return self._last_frame()
    views, _ = self._step(action)
    return self._frame_dict(views)

  def collect(self, seed: int) -> dict:
    """Runs the oracle expert from `seed` until success or the horizon; the whole episode dict
    (roboshape/sim/__init__.py)."""
    np = self.np
    views = [self._reset(seed)]
    states, actions, rewards = [self._state], [], []
    while not self.done:
      action = self.expert.act(self.task.privileged_state()).cpu().numpy().astype(np.float32)[0]
      frame, reward = self._step(action)
      views.append(frame)
      states.append(self._state)
      actions.append(action)
      rewards.append(reward)
    episode = dict(task=self.spec["task"], level=self.spec["level"], seed=int(seed), success=self.success,
                   env_version=self.env_version, terminated=self.success,
                   state=np.stack(states).astype(np.float32),
                   action=np.stack(actions).astype(np.float32).reshape(-1, 7),
                   reward=np.asarray(rewards, np.float32))
    for key in views[0]:                   # each camera's image, segmentation (and depth), same dtypes
      episode[key] = np.stack([v[key] for v in views])
    return episode


def serve(conn, spec: dict) -> int:
  """The request loop; returns the process exit code."""
  try:
    worker = Worker(spec)
  except Exception as e:  # pylint: disable=broad-except
    traceback.print_exc()
    from roboshape import envs  # pylint: disable=import-outside-toplevel
    conn.send(("error", envs.explain_construction_error(e)))
    return 1
  conn.send(("ok", worker.info()))
  while True:
    try:
      command, arg = conn.recv()
    except (EOFError, OSError):  # the parent went away
      return 0
    if command == "close":
      conn.send(("ok", None))
      return 0
    if command == "_crash":  # test hook: die the way a segfaulting simulator would
      print(f"roboshape worker: crashing on request: {arg}", file=sys.stderr, flush=True)
      os._exit(3)  # pylint: disable=protected-access
    try:
      if command not in ("collect", "reset", "step"):
        raise ValueError(f"unknown worker command {command!r}")
      reply = ("ok", getattr(worker, command)(arg))
    except Exception as e:  # pylint: disable=broad-except
      traceback.print_exc()
      reply = ("error", f"{command}({arg if command != 'step' else '...'}) failed: {_one_line(e)}")
    conn.send(reply)


def main(argv) -> int:
  from multiprocessing.connection import Connection  # pylint: disable=import-outside-toplevel
  conn = Connection(int(argv[1]))
  return serve(conn, json.loads(argv[2]))


if __name__ == "__main__":
  sys.exit(main(sys.argv))
