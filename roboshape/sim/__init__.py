"""The numpy bridge to the simulator (contract A): EnvSpec, SimPool and SimWorkerError.

Importing this package never imports sapien or mani_skill; workers are separate processes (roboshape/sim/worker.py).
"""
from roboshape.sim.pool import SimPool, SimWorkerError
from roboshape.sim.spec import EnvSpec, check_seeds

__all__ = ["EnvSpec", "SimPool", "SimWorkerError", "check_seeds"]
