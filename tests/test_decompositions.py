"""roboshape/report/decompositions.py: the report's per-object decomposition table, from the files runs leave."""
import json
import os

from roboshape import rundir
from roboshape.report import decompositions


def _write(path, data):
  os.makedirs(os.path.dirname(path), exist_ok=True)
  with open(path, "w") as f:
    json.dump(data, f)


def test_the_table_reads_published_and_workdir_validations_and_marks_what_is_absent(tmp_path):
  published, workdir = str(tmp_path / "push_savi"), str(tmp_path / "pick_savi")
  _write(os.path.join(published, "savi_val_metrics.json"),
         [dict(step=1, fg_ari=0.1, miou=0.1), dict(step=2, fg_ari=0.812, miou=0.3, cube_iou=0.555, cube_found=0.8,
                                                   goal_iou=0.9, hand_iou=float("nan"))])
  seeds = dict(selected_seed=1, metric="fg_ari", seeds=[dict(seed=0, fg_ari=0.2, miou=0.1),
                                                        dict(seed=1, fg_ari=0.5, miou=0.25)])
  _write(rundir.selection_path(rundir.pretrain_dir(workdir, "savi")), seeds)
  runs = [("push", "savi", published), ("pick", "savi+proprio", workdir), ("push", "state", published),
          ("place", "savi", str(tmp_path / "absent"))]
  lines = decompositions.table(runs, lambda column: column.upper())
  assert lines[0] == "| | FG-ARI | mIoU | cube IoU | cube found | target IoU | hand IoU |"
  assert lines[2:] == ["| push x SAVI | 0.81 | 0.30 | 0.56 | 80% | 0.90 | - |",
                       "| pick x SAVI+PROPRIO | 0.50 | 0.25 | - | - | - | - |"]
  assert decompositions.table([("push", "state", published)], str) == []
