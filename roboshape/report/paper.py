"""The seed paper's success rates, per task x encoder x level (its Tables of Push cube and Pick cube: mean ± std over
its three runs of 100 rollouts; Place cube in bin: none of its models succeeded, stated in its text without a
table), so a report can set every cell beside the paper's and say why a column the paper has is absent here."""
from typing import Dict, Tuple

ENCODERS = ("dino", "r3m", "savi")     # the paper's columns
_LEVELS = ("train", "L1", "L2", "L3")


def _rows(**columns) -> Dict[Tuple[str, str], Tuple[float, float]]:
  return {(level, encoder): value for encoder, values in columns.items() for level, value in zip(_LEVELS, values)}


_ZERO = ((0.0, 0.0),) * 4
TABLES = {
    "push": _rows(dino=_ZERO, r3m=((0.88, 0.07), (0.26, 0.06), (0.70, 0.01), (0.76, 0.01)),
                  savi=((0.69, 0.06), (0.55, 0.02), (0.60, 0.04), (0.56, 0.08))),
    "pick": _rows(dino=_ZERO, r3m=_ZERO, savi=((0.56, 0.01), (0.44, 0.04), (0.48, 0.07), (0.51, 0.02))),
    "place": _rows(dino=_ZERO, r3m=_ZERO, savi=_ZERO),
}
SOURCE = {"push": "its Table of Push cube", "pick": "its Table of Pick cube",
          "place": "no model succeeded, said in its text, which gives no table"}
