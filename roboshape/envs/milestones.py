"""The steps on the way to each task's success, in order, by name: pure python, no simulator.

The task classes (tasks.py) say when each milestone holds; closed-loop evaluation records which ones every rollout
reached, so a failure reads as how far it got. roboshape.envs re-exports the table as `envs.MILESTONES`.
"""
MILESTONES = {"push": ("moved", "halfway", "on_target"), "pick": ("grasped", "lifted", "at_point"),
              "place": ("grasped", "lifted", "over_bin", "in_bin")}
