"""Success rates with 95% intervals that respect how an evaluation is built; the difference between two encoders;
robustness to a shift; and how many more rollouts or training seeds would decide a difference. Pure numpy.

How an evaluation is built (roboshape/eval/closed_loop.py). A cell (one task x encoder) holds the policies of its T
training seeds (policy.train_seeds; one policy when it has none), and every policy plays the same start states at
every level: rollout r of evaluation seed s has env seed `offset + s * 100_000 + r` whatever the training seed, the
level or the encoder, and that seed alone keys the layout, what the level draws and the policy's sampling. A cell's
rollouts of one level are thus a table of T policies x K start states (crossed, not nested), and two cells of one task
share their start states.

The hierarchical bootstrap. Each resample draws, with replacement,
  1. the cell's training seeds (T of T), first, because the claims are about an encoder trained by a recipe, not
     about one trained policy, and policies of one recipe (another initialisation and data order) can differ
     beyond what their rollouts show of each;
  2. then the start states (K of K), one draw shared by every drawn training seed (they played the same layouts),
     by every level (the same layouts again) and by both cells of a comparison where their env seeds match;
and the resampled rate pools the drawn (policy, start state) rollouts, each counted as often as both were drawn.
  - The start state, not the evaluation seed, is the second stage's unit: an evaluation seed is a block of env seeds
    that share nothing but the block's index, so its rollouts are already independent draws of a start state, and
    resampling the blocks and then the rollouts within them would count the rollout-to-rollout variation twice (an
    interval about sqrt(2) too wide). Env seeds, not positions, say which rollouts of two cells match.
  - Drawing the start states anew for each training seed would count T x K rollouts as T x K independent layouts,
    while a layout that is hard for one policy is the same layout for the others: too narrow an interval.
  - Resampling both ways of a crossed table counts the policy x start-state interaction through both draws, so
    the interval errs on the wide side, never the narrow one.
  - A cell with one training seed: stage 1 always draws that seed, so the interval holds the start states'
    variation only, not the variation between training seeds. It is then narrower than the cell's uncertainty, and
    `Estimate.one_seed` says so for the report to say it.
The interval is the 2.5th to 97.5th percentile of DRAWS resamples from np.random.default_rng(seed): the same seed
gives the same numbers. A rollout lost to a simulator crash is missing from the table and from every resample.

Statistics of the resampled rates (`estimate`): one cell's success at a level (`success`); the difference of two
cells' success averaged over some levels (`difference`, paired through the shared start states); robustness, a
cell's success averaged over shift levels divided by its success at the train level (`robustness`), and the
difference of two cells' robustness (`robustness_difference`). A ratio whose train-level success is 0 is undefined:
the observed value is NaN when the table's is 0, and when more than 2.5% of the resamples have a train-level success
of 0 the interval is undefined too (NaN): the percentiles of the rest would describe a different question.

How many more would decide it (`needed`). A difference is decided when its interval leaves 0. Take h, the larger
of the interval's half-width on 0's side (value - low, or high - value for a negative value) and 1.96 standard
deviations of the resamples (a percentile interval of rates near 0 is squeezed against 0, so its own half-width can
understate the spread), and V_T and V_K, the resamples' variance when only the training seeds or only the start
states are drawn. The projected half-width with T' training seeds and K' start states is
    h(T', K') = h * sqrt(f_T * T / T' + f_K * K / K'),   f_T = V_T / (V_T + V_K),  f_K = V_K / (V_T + V_K),
each share of the variance falling with the number of units it comes from. The difference becomes decidable, if it
held at its observed value, where h(T', K') < |value|: `needed` gives K' with T as now, T' with K as now (each None
where that alone cannot get there, or where a cell has one training seed so V_T is unmeasured: K' is then a lower
bound), and the factor by which multiplying both gets there.
"""
import dataclasses
import math
from typing import Callable, Dict, Iterable, Optional, Sequence, Tuple

import numpy as np

DRAWS = 4000
ALPHA = 0.05                 # a 95% interval
SEED = 0                     # the report's resampling seed
TRAIN = "train"              # the level shifts are relative to
EPS = 1e-12                  # a bound within this of 0 counts as 0 (rounding of sums of rates)


@dataclasses.dataclass(frozen=True)
class Cell:
  """One task x encoder's rollouts.

  Attributes:
    levels: the levels it has, in first-seen order.
    train_seeds: the training seeds' labels, sorted (None for a cell without training seeds).
    starts: the env seeds of its rollouts, sorted (a start state is the same env seed at every level).
    success: float [len(levels), len(train_seeds), len(starts)]: 1.0 or 0.0, NaN where no rollout counts (none
      was run, or it was lost to a simulator crash).
  """
  levels: Tuple[str, ...]
  train_seeds: Tuple
  starts: Tuple[int, ...]
  success: np.ndarray


def cell(rollouts: Iterable[Dict]) -> Cell:
  """The Cell of one task x encoder's rollout records ({level, seed, success, ended, train_seed (optional)})."""
  rollouts = [r for r in rollouts]
  levels = tuple(dict.fromkeys(r["level"] for r in rollouts))
  train_seeds = tuple(sorted({r.get("train_seed") for r in rollouts}, key=lambda s: (s is not None, s)))
  starts = tuple(sorted({int(r["seed"]) for r in rollouts}))
  index = ({l: i for i, l in enumerate(levels)}, {t: i for i, t in enumerate(train_seeds)},
           {s: i for i, s in enumerate(starts)})
  success = np.full((len(levels), len(train_seeds), len(starts)), np.nan)
  for r in rollouts:
    if r["ended"] != "worker_crash":
      success[index[0][r["level"]], index[1][r.get("train_seed")], index[2][int(r["seed"])]] = float(
          bool(r["success"]))
  return Cell(levels, train_seeds, starts, success)


@dataclasses.dataclass(frozen=True)
class Estimate:
  """A statistic of one or more cells with its bootstrap interval.

  Attributes:
    value: the statistic on the cells' rollouts as they are (NaN: undefined).
    low, high: the 95% percentile interval (NaN: undefined).
    undefined: the share of resamples where the statistic is undefined.
    var: the resamples' variance (over those where the statistic is defined; NaN where none is).
    var_seeds, var_starts: the same when only the training seeds, or only the start states, are drawn.
    seeds: each cell's number of training seeds.
    starts: the number of start states (env seeds) the cells hold between them.
  """
  value: float
  low: float
  high: float
  undefined: float
  var: float
  var_seeds: float
  var_starts: float
  seeds: Tuple[int, ...]
  starts: int

  @property
  def one_seed(self) -> bool:
    """Whether a cell has one training seed, so the interval leaves out the variation between training seeds."""
    return min(self.seeds) == 1

  @property
  def defined(self) -> bool:
    return not (math.isnan(self.low) or math.isnan(self.value))

  @property
  def side(self) -> int:
    """+1 when the interval lies above 0, -1 when below, 0 when it holds 0 or is undefined."""
    if not self.defined:
      return 0
    return 1 if self.low > EPS else -1 if self.high < -EPS else 0


def _weights(rng: np.random.Generator, n: int, draws: int) -> np.ndarray:
  """[draws, n] counts: how often each of n units is drawn in n draws with replacement."""
  return rng.multinomial(n, np.full(n, 1.0 / n), size=draws).astype(float)


def rates(cells: Sequence[Cell], levels: Sequence[str], draws: int = DRAWS, seed: int = SEED,
          resample: Tuple[bool, bool] = (True, True)) -> np.ndarray:
  """[draws, len(cells), len(levels)] resampled success rates (NaN where a resample holds no rollout).

  resample: (draw the training seeds, draw the start states); a stage not drawn keeps every unit once. draws=0
  gives the rates of the rollouts as they are, [1, len(cells), len(levels)]."""
  starts = sorted(set().union(*(c.starts for c in cells)))
  rng = np.random.default_rng(seed)
  n = max(draws, 1)
  w = _weights(rng, len(starts), n) if draws and resample[1] else np.ones((n, len(starts)))
  out = np.full((n, len(cells), len(levels)), np.nan)
  for i, c in enumerate(cells):
    columns = np.searchsorted(starts, c.starts)
    v = _weights(rng, len(c.train_seeds), n) if draws and resample[0] else np.ones((n, len(c.train_seeds)))
    for j, level in enumerate(levels):
      if level not in c.levels:
        continue
      y = c.success[c.levels.index(level)]                       # [T, K]
      present = (~np.isnan(y)).astype(float)
      wk = w[:, columns]
      total = np.einsum("bt,tk,bk->b", v, present, wk)
      hits = np.einsum("bt,tk,bk->b", v, np.nan_to_num(y), wk)
      out[:, i, j] = np.where(total > 0, hits / np.where(total > 0, total, 1), np.nan)
  return out


def estimate(cells: Sequence[Cell], levels: Sequence[str], statistic: Callable[[np.ndarray], np.ndarray],
             draws: int = DRAWS, seed: int = SEED) -> Estimate:
  """`statistic` ([B, cells, levels] rates -> [B], NaN where undefined) of the cells, with its interval."""
  def run(resample):
    return statistic(rates(cells, levels, draws if any(resample) else 0, seed, resample))
  value = float(run((False, False))[0])
  full = run((True, True))
  finite = full[np.isfinite(full)]
  undefined = 1.0 - finite.size / full.size
  if finite.size and undefined <= ALPHA / 2:
    low, high = (float(q) for q in np.percentile(finite, [100 * ALPHA / 2, 100 * (1 - ALPHA / 2)]))
  else:
    low = high = float("nan")

  def variance(samples):
    samples = samples[np.isfinite(samples)]
    return float(np.var(samples)) if samples.size else float("nan")
  return Estimate(value=value if math.isfinite(value) else float("nan"), low=low, high=high, undefined=undefined,
                  var=variance(full), var_seeds=variance(run((True, False))), var_starts=variance(run((False, True))),
                  seeds=tuple(len(c.train_seeds) for c in cells),
                  starts=len(set().union(*(c.starts for c in cells))))


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
  """numerator / denominator, NaN where the denominator is 0 (or NaN)."""
  return np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1), np.nan)


def success(c: Cell, level: str, draws: int = DRAWS, seed: int = SEED) -> Estimate:
  """The cell's success at `level`, pooled over its rollouts there."""
  return estimate([c], [level], lambda r: r[:, 0, 0], draws, seed)


def difference(a: Cell, b: Cell, levels: Sequence[str], draws: int = DRAWS, seed: int = SEED) -> Estimate:
  """a's success minus b's, each averaged over `levels`; the start states are drawn once for both cells."""
  return estimate([a, b], levels, lambda r: r[:, 0].mean(axis=1) - r[:, 1].mean(axis=1), draws, seed)


def robustness(c: Cell, shifts: Sequence[str], draws: int = DRAWS, seed: int = SEED) -> Estimate:
  """The cell's success averaged over `shifts` divided by its success at the train level (undefined where that is 0).
  The same policies and start states are drawn for every level."""
  return estimate([c], [TRAIN] + list(shifts), lambda r: _ratio(r[:, 0, 1:].mean(axis=1), r[:, 0, 0]), draws, seed)


def robustness_difference(a: Cell, b: Cell, shifts: Sequence[str], draws: int = DRAWS,
                          seed: int = SEED) -> Estimate:
  """a's robustness minus b's (`robustness`), both from one draw of the start states."""
  def statistic(r):
    return (_ratio(r[:, 0, 1:].mean(axis=1), r[:, 0, 0]) - _ratio(r[:, 1, 1:].mean(axis=1), r[:, 1, 0]))
  return estimate([a, b], [TRAIN] + list(shifts), statistic, draws, seed)


@dataclasses.dataclass(frozen=True)
class Needed:
  """What would make an undecided difference decidable if it held at its observed value (see the module docstring).

  Attributes:
    starts: start states (rollouts per level per training seed) with the training seeds as now; None where more
      rollouts alone cannot get there.
    seeds: training seeds per cell with the rollouts as now; None where more training seeds alone cannot get there
      or a cell has one training seed (its variance between training seeds unmeasured).
    factor: the factor by which multiplying both the rollouts and the training seeds gets there.
    lower_bound: True when a cell has one training seed, so `starts` leaves out the training seeds' variation.
  """
  starts: Optional[int]
  seeds: Optional[int]
  factor: float
  lower_bound: bool


def needed(e: Estimate) -> Optional[Needed]:
  """How many more rollouts or training seeds would decide `e`; None when it is decided already, undefined, 0, or
  without any resampling variance."""
  if not e.defined or e.side != 0 or abs(e.value) <= EPS:
    return None
  half = max(e.value - e.low if e.value > 0 else e.high - e.value, 1.96 * math.sqrt(e.var))
  total = e.var_seeds + e.var_starts
  if not total > 0 or not half > 0:
    return None
  q = (abs(e.value) / half) ** 2                    # <= 1 while undecided
  f_seeds, f_starts = e.var_seeds / total, e.var_starts / total
  seeds = max(e.seeds)

  def beyond(now: int, share: float, rest: float) -> Optional[int]:
    if q <= rest:
      return None
    return max(now + 1, math.ceil(now * share / (q - rest)))
  return Needed(starts=beyond(e.starts, f_starts, f_seeds),
                seeds=None if e.one_seed else beyond(seeds, f_seeds, f_starts),
                factor=1.0 / q, lower_bound=e.one_seed)
