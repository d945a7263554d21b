"""Tests of the report's intervals and verdict (roboshape/report/stats.py, roboshape/report/claims.py) on synthetic cells
whose answers are known, and of the report that prints them (roboshape/report/report.py)."""
import math
import os

import numpy as np
import pytest

from roboshape.report import claims
from roboshape.report import plots
from roboshape.report import report
from roboshape.report import results as results_lib
from roboshape.report import stats


def _rollouts(task, encoder, wins, starts=60, train_seeds=(None,), first_seed=0):
  """Rollout records of one cell: wins[(train_seed, level)] is the set of start indices (0..starts-1) that succeed;
  start k has env seed first_seed + k at every level and training seed, as closed_loop's seed scheme has it."""
  levels = list(dict.fromkeys(level for _, level in wins))
  return [dict(task=task, encoder=encoder, train_seed=t, level=level, seed_index=k // 20, rollout=k % 20,
               seed=first_seed + k, success=k in wins.get((t, level), ()), length=9, ended="horizon")
          for t in train_seeds for level in levels for k in range(starts)]


def _cell(wins, **kwargs):
  return stats.cell(_rollouts("push", "savi", wins, **kwargs))


def _half(e):
  return (e.high - e.low) / 2


def test_all_successes_give_the_interval_one_to_one():
  c = _cell({(t, "train"): range(20) for t in (0, 1, 2)}, starts=20, train_seeds=(0, 1, 2))
  e = stats.success(c, "train")
  assert (e.value, e.low, e.high, e.undefined, e.seeds, e.starts) == (1.0, 1.0, 1.0, 0.0, (3,), 20)
  assert e.side == 1 and not e.one_seed


def test_many_rollouts_of_one_half_give_the_binomial_half_width():
  n = 2000
  e = stats.success(_cell({(None, "train"): range(0, n, 2)}, starts=n), "train")
  assert e.value == 0.5 and e.one_seed
  assert _half(e) == pytest.approx(1.96 * math.sqrt(0.25 / n), rel=0.1)
  assert (e.low + e.high) / 2 == pytest.approx(0.5, abs=0.003)


def test_training_seeds_that_disagree_widen_the_interval_and_more_that_agree_narrow_it():
  rng = np.random.default_rng(3)
  one = stats.success(_cell({(None, "train"): range(30)}), "train")
  # three policies at 0.2, 0.5 and 0.8 on the same 60 start states: their disagreement is in the interval
  spread = stats.success(_cell({(0, "train"): range(12), (1, "train"): range(30), (2, "train"): range(48)},
                               train_seeds=(0, 1, 2)), "train")
  # three policies at 0.5 each, on other start states of the 60: more rollouts, little between them
  agree = stats.success(_cell({(t, "train"): set(rng.permutation(60)[:30].tolist()) for t in (0, 1, 2)},
                              train_seeds=(0, 1, 2)), "train")
  assert one.value == spread.value == agree.value == 0.5
  assert one.one_seed and not spread.one_seed
  assert _half(spread) > 1.5 * _half(one) and _half(agree) < 0.95 * _half(one)
  # one training seed: the training-seed stage draws nothing
  assert one.var_seeds == 0 and spread.var_seeds > one.var_starts


def test_the_bootstrap_is_the_same_for_the_same_seed_and_another_for_another():
  c = _cell({(t, "train"): range(10 * t, 10 * t + 25) for t in (0, 1)}, train_seeds=(0, 1))
  assert np.array_equal(stats.rates([c], ["train"], 200, seed=5), stats.rates([c], ["train"], 200, seed=5))
  assert not np.array_equal(stats.rates([c], ["train"], 200, seed=5), stats.rates([c], ["train"], 200, seed=6))
  assert stats.success(c, "train", seed=5) == stats.success(c, "train", seed=5)


def test_a_crashed_rollout_counts_in_no_rate():
  records = _rollouts("push", "savi", {(None, "train"): {0, 1}}, starts=4)
  records[0]["ended"] = "worker_crash"                 # start 0 succeeded before its worker died: left out
  c = stats.cell(records)
  assert np.isnan(c.success[0, 0, 0]) and stats.success(c, "train").value == pytest.approx(1 / 3)


def test_the_paired_difference_has_the_sign_of_the_better_cell_and_pairing_narrows_it():
  a = _cell({(None, "train"): range(30)})
  b = _cell({(None, "train"): range(20)})
  ab, ba = stats.difference(a, b, ["train"]), stats.difference(b, a, ["train"])
  assert ab.value == pytest.approx(1 / 6) and ab.side == 1 and ba.value == pytest.approx(-1 / 6) and ba.side == -1
  assert (ab.low, ab.high) == pytest.approx((-ba.high, -ba.low))
  # the same outcomes on start states that do not match (other env seeds): drawn apart, the interval holds 0
  apart = stats.difference(a, _cell({(None, "train"): range(20)}, first_seed=1000), ["train"])
  assert apart.value == pytest.approx(1 / 6) and apart.starts == 120 and apart.side == 0
  assert _half(apart) > 1.5 * _half(ab)          # analytically sqrt((.25 + .22) / (5/36)) = 1.85 times


def test_robustness_is_the_shift_over_the_train_level_and_undefined_at_a_train_success_of_zero():
  c = _cell({(None, "train"): range(30), (None, "L1"): range(15), (None, "L2"): range(30)})
  assert stats.robustness(c, ["L1"]).value == pytest.approx(0.5)
  assert stats.robustness(c, ["L1", "L2"]).value == pytest.approx(0.75)
  never = stats.robustness(_cell({(None, "train"): (), (None, "L1"): range(10)}), ["L1"])
  assert math.isnan(never.value) and math.isnan(never.low) and never.undefined == 1 and never.side == 0
  assert claims.interval(never) == "undefined"
  # one train-level success in 60: a value, but most resamples draw none, so no interval
  once = stats.robustness(_cell({(None, "train"): {7}, (None, "L1"): {7, 8}}), ["L1"])
  assert once.value == 2 and once.undefined > stats.ALPHA / 2 and not once.defined
  assert claims.interval(once) == "2.00 [no interval]†"
  assert stats.needed(once) is None


def test_needed_projects_the_rollouts_that_would_decide_an_undecided_difference():
  # 12 vs 6 successes in 60 on different start states: per start the difference is +1, -1 or 0 (variance 0.29),
  # so the normal half-width 1.96 * sqrt(0.29 / K) falls below 0.1 at K = 1.96^2 * 0.29 / 0.01 = 111
  a = _cell({(None, "train"): range(12)})
  b = _cell({(None, "train"): range(12, 18)})
  e = stats.difference(a, b, ["train"])
  assert e.value == pytest.approx(0.1) and e.side == 0
  n = stats.needed(e)
  assert 95 <= n.starts <= 130 and n.seeds is None and n.lower_bound
  # decided differences need nothing more
  assert stats.needed(stats.difference(_cell({(None, "train"): range(40)}), b, ["train"])) is None
  # three training seeds a cell: half-width 0.12 for a difference of 0.1, so q = (0.1 / 0.12)^2 = 0.694 and both
  # ways together need 1 / q = 1.44 times; mostly start states' variance (0.8): 60 * 0.8 / (0.694 - 0.2) = 97.2
  # start states, and no number of training seeds alone, since their share (0.2) is not what keeps it undecided
  def projected(share_seeds):
    var = (0.12 / 1.96) ** 2
    return stats.needed(stats.Estimate(value=0.1, low=-0.02, high=0.22, undefined=0.0, var=var,
                                       var_seeds=share_seeds * var, var_starts=(1 - share_seeds) * var,
                                       seeds=(3, 3), starts=60))
  assert projected(0.2) == stats.Needed(starts=98, seeds=None, factor=pytest.approx(1.44), lower_bound=False)
  # mostly training seeds' variance: 3 * 0.8 / (0.694 - 0.2) = 4.86 training seeds, no number of start states
  assert projected(0.8) == stats.Needed(starts=None, seeds=5, factor=pytest.approx(1.44), lower_bound=False)


def test_the_verdict_gives_no_projection_beyond_a_hundredfold():
  # a difference of 0.01 with half-width 0.12: q = (0.01 / 0.12)^2, so 144 times both; the verdict says only that
  # it is beyond 100 times, and the projection below the bound is still printed in full
  def said(value, seeds):
    var = (0.12 / 1.96) ** 2
    e = stats.Estimate(value=value, low=value - 0.12, high=value + 0.12, undefined=0.0, var=var,
                       var_seeds=0.5 * var, var_starts=0.5 * var, seeds=seeds, starts=60)
    return claims._needed(e)  # pylint: disable=protected-access
  assert said(0.01, (3, 3)) == ("; if the difference held, it would take more than 100 times both the rollouts and "
                                "the training seeds to decide it")
  assert said(-0.01, (1, 3)) == "; if the difference held, it would take more than 100 times the rollouts to decide it"
  assert said(0.1, (3, 3)).endswith("or 1.4 times both the rollouts and the training seeds")


def _loaded(rates_by_cell, starts=40):
  """{(task, encoder): run} with one training seed, start k succeeding at a level when k < rate * starts."""
  return {(task, encoder): dict(rollouts=_rollouts(task, encoder, {(None, level): range(round(r * starts))
                                                                   for level, r in levels.items()}, starts=starts))
          for (task, encoder), levels in rates_by_cell.items()}


def test_the_verdict_says_supports_contradicts_or_cannot_decide_from_the_cells():
  loaded = _loaded({
      ("push", "savi"): dict(train=0.8, L1=0.8), ("push", "ae"): dict(train=0.8, L1=0.1),
      ("pick", "savi"): dict(train=0.8, L1=0.1), ("pick", "ae"): dict(train=0.8, L1=0.8),
      ("place", "savi"): dict(train=0.5, L1=0.5), ("place", "ae"): dict(train=0.5, L1=0.45)})
  a = claims.answer(loaded, ["push", "pick", "place"], ["ae", "savi"], ["train", "L1"])
  text = claims.verdict(a, ["push", "pick", "place"], ["ae", "savi"])
  claim1, claim2 = text.split("\n\n")
  flat = " ".join(text.split())
  for claim in (claim1, claim2):
    assert "So this table supports claim " in claim and "on push, contradicts it on pick and cannot decide it " \
        "on place." in claim
  # place: +0.5 on 2 of 40 start states, so the bootstrap's variance of the difference is 0.011875 * 39 / 40 / 40
  # and 1.96 of its sd falls below 0.025 at 1.96^2 * 0.011875 * 39 / 40 / 0.025^2 = 71.2 start states (the
  # resamples' own variance, seeded, sets the last digit)
  # (SAVi 0.50, AE (0.5 + 0.45) / 2, which is 0.47499... in floating point)
  assert "place, SAVi − AE: +0.03 [+0.00, +0.06]† (SAVi 0.50, AE 0.47 over the levels): cannot decide; if the " \
      "difference held, it would be decided with " \
      "about 71 rollouts per level per training seed (now 40; at least, as the variation between training seeds " \
      "is not counted)." in flat
  assert "it would be decided with about" in claim2.split("place, ")[1]
  assert "DINO and R3M: no cell in this table (skipped or not run), so the claim is judged against AE only." in flat
  assert "On push, pick and place a cell has one training seed" in flat
  # a table without SAVi decides nothing, and says why
  lonely = claims.answer(_loaded({("push", "ae"): dict(train=0.5, L1=0.5)}), ["push"], ["ae"], ["train", "L1"])
  assert "This table cannot decide claim 1: it holds no SAVi cell" in claims.verdict(lonely, ["push"], ["ae"])
  # a table without a global encoder says they are absent, and judges against none of them
  alone = claims.verdict(claims.answer(_loaded({("push", "savi"): dict(train=0.5, L1=0.5)}), ["push"], ["savi"],
                                       ["train", "L1"]), ["push"], ["savi"])
  assert "DINO, R3M and AE: no cell in this table (skipped or not run). This table cannot decide claim 1" in \
      " ".join(alone.split()) and "judged against nothing" not in alone


def test_claim_1_reads_savi_beside_the_state_control_over_the_levels_both_have():
  loaded = _loaded({("pick", "savi"): dict(train=0.1, L1=0.025, L2=0.0), ("pick", "ae"): dict(train=0.0, L1=0.0),
                    ("pick", "state"): dict(train=1.0, L1=0.9)})
  a = claims.answer(loaded, ["pick"], ["ae", "savi", "state"], ["train", "L1", "L2"])
  claim1, claim2 = claims.verdict(a, ["pick"], ["ae", "savi", "state"]).split("\n\n")
  # over train and L1, the levels the state cell has: state (1.0 + 0.9) / 2 = 0.95, SAVi (0.1 + 0.025) / 2, and
  # the paper's SAVi on pick (0.56 + 0.44) / 2
  assert ("The privileged state (the control that should succeed) succeeds 0.95 over the same levels on pick, "
          "SAVi 0.06 (the paper's SAVi 0.50).") in " ".join(claim1.split())
  # a level the paper has not (here "L9") leaves the paper's figure out rather than average other levels
  odd = _loaded({("pick", "savi"): dict(train=0.1, L9=0.0), ("pick", "ae"): dict(train=0.0, L9=0.0),
                 ("pick", "state"): dict(train=1.0, L9=1.0)})
  flat = " ".join(claims.verdict(claims.answer(odd, ["pick"], ["ae", "savi", "state"], ["train", "L9"]), ["pick"],
                                 ["ae", "savi", "state"]).split())
  assert "over the same levels on pick, SAVi 0.05." in flat and "the paper's" not in flat
  assert "privileged state" not in claim2
  # without a state cell, no such sentence
  del loaded[("pick", "state")]
  assert "privileged state" not in claims.verdict(claims.answer(loaded, ["pick"], ["ae", "savi"], ["train", "L1"]),
                                                  ["pick"], ["ae", "savi"])


def test_encoders_that_never_succeed_cannot_be_separated_nor_their_robustness_compared():
  loaded = _loaded({("place", "savi"): dict(train=0.0, L1=0.0), ("place", "ae"): dict(train=0.0, L1=0.0)})
  flat = " ".join(claims.verdict(claims.answer(loaded, ["place"], ["ae", "savi"], ["train", "L1"]), ["place"],
                                 ["ae", "savi"]).split())
  assert "neither succeeds in any rollout, so no number of rollouts separates them" in flat
  assert "SAVi never succeeds at the train level, so its robustness is undefined" in flat
  assert flat.count("cannot decide claim") == 2


def test_an_option_is_read_against_its_plain_encoder_on_the_same_start_states():
  encoders = ["ae", "ae+proprio", "savi", "savi+proprio"]
  loaded = _loaded({("push", "savi"): dict(train=0.5, L1=0.5), ("push", "savi+proprio"): dict(train=1.0, L1=1.0),
                    ("push", "ae"): dict(train=0.5, L1=0.5), ("push", "ae+proprio"): dict(train=0.5, L1=0.5),
                    ("pick", "savi+proprio"): dict(train=0.5, L1=0.5)})     # pick: no plain SAVi to read it against
  a = claims.answer(loaded, ["push", "pick"], encoders, ["train", "L1"])
  assert claims.with_options(encoders) == [("ae+proprio", "ae"), ("savi+proprio", "savi")]
  assert claims.with_options(["savi+proprio", "ae"]) == [] and not any(k[0] == "pick" for k in a.options)
  helped = a.options[("push", "savi+proprio", claims.LEVELS_MEAN)]   # starts 20..39 succeed only with the option
  assert helped.value == pytest.approx(0.5) and helped.side == 1 and helped.low > 0.3
  same = a.options[("push", "ae+proprio", claims.LEVELS_MEAN)]       # the same starts succeed: 0 in every resample
  assert same.value == same.low == same.high == 0.0 and same.side == 0
  flat = " ".join(claims.verdict(a, ["push", "pick"], encoders).split())
  assert f"push, SAVi+proprio − SAVi: {claims.interval(helped, signed=True)}: helps." in flat
  assert ("push, AE+proprio − AE: +0.00 [+0.00, +0.00]†: not shown to differ; the observed difference is 0, so no "
          "number of rollouts would decide it.") in flat
  assert flat.index("**Claim 2") < flat.index("**Options beyond the paper**")
  table = claims.options_table(a, "push", encoders)
  assert len(table.splitlines()) == 4 and "| SAVi+proprio − SAVi |" in table
  assert claims.options_table(a, "pick", encoders) == ""
  plain = claims.answer(loaded, ["push"], ["ae", "savi"], ["train", "L1"])
  assert "Options beyond" not in claims.verdict(plain, ["push"], ["ae", "savi"])   # none without such a column


def test_the_published_report_prints_intervals_comparisons_robustness_the_figure_and_the_verdict(tmp_path):
  root = tmp_path / "results"
  for (task, encoder), run in _loaded({("push", "savi"): dict(train=0.8, L1=0.8, L2=0.5),
                                       ("push", "ae"): dict(train=0.8, L1=0.1, L2=0.2),
                                       ("push", "objects"): dict(train=0.5, L1=0.5, L2=0.5)}).items():
    os.makedirs(root / f"{task}_{encoder}")
    results_lib.write_csv(str(root / f"{task}_{encoder}" / "results.csv"), run["rollouts"])
  assert report.main(["report", str(root)]) == 0
  md = (root / "report" / "report.md").read_text()
  assert md.index("## Verdict") < md.index("## push") < md.index("### push: success with its 95% interval")
  assert "| none | 0.80 [0.68, 0.93]† | 0.80 [0.68, 0.93]† | 0.50 [0.35, 0.65]† |" in md
  assert "| SAVi − AE | +0.00 [+0.00, +0.00]† | +0.70 [" in md and "| SAVi − Objects | +0.30 [" in md
  assert "| SAVi | 1.00 [1.00, 1.00]† | 0.62 [" in md and "mean over L1, L2 |" in md
  assert md.count("\n| L3 |") == 2                      # the table's row of "-" and the paper's; no interval row
  # the paper's push table beside ours, and why its columns that have no cell here are absent
  assert "| none | 0.00 ± 0.00 | **0.88** ± 0.07 | 0.69 ± 0.06 |" in md
  assert ("- the paper's R3M column has no cell here (not in this report's runs; the grid skips a baseline whose "
          "weights are absent).") in md
  assert "- the paper's SAVi column has no cell here" not in md
  assert "| SAVi − AE |  |  | +0.62 [" in md           # (0.8 + 0.5) / 1.6 - (0.1 + 0.2) / 1.6
  assert "So this table supports claim 1 on push." in md and "So this table supports claim 2 on push." in md
  # each one's success over the levels beside the difference, and the control's: (0.8 + 0.8 + 0.5) / 3 = 0.70,
  # (0.8 + 0.1 + 0.2) / 3 = 0.37, objects 0.50
  assert "push, SAVi − AE: +0.33 [" in md and "(SAVi 0.70, AE 0.37 over the levels): supports." in md
  assert "On push the ground-truth object tokens (the control) succeed 0.50 over the levels, SAVi − Objects +0.20 [" \
      in md
  assert os.path.getsize(root / "report" / "success_by_level.png") > 0
  # the same cells give the same report
  assert report.main(["report", str(root)]) == 0 and (root / "report" / "report.md").read_text() == md


def test_the_figures_bars_are_the_tasks_cells_side_by_side_each_encoder_in_one_colour():
  encoders = ["dino", "r3m", "ae", "ae+proprio", "savi", "savi+proprio", "objects", "state"]
  cell = (0.5, 0.4, 0.6)
  values = {("push", e, l): cell for e in ("ae", "savi", "objects") for l in ("train", "L1")}
  values[("pick", "savi", "L1")] = cell                        # one level is enough for a bar
  push = plots.bar_layout(values, "push", encoders, ["train", "L1"])
  assert [(e, c) for e, _, _, c in push] == [("ae", 2), ("savi", 4), ("objects", 6)]
  assert [o for _, o, _, _ in push] == pytest.approx([-0.8 / 3, 0.0, 0.8 / 3])   # no gaps for absent columns
  assert [w for _, _, w, _ in push] == pytest.approx([0.8 / 3] * 3)
  assert plots.bar_layout(values, "pick", encoders, ["train", "L1"]) == [("savi", 0.0, 0.8, 4)]
  assert plots.bar_layout(values, "place", encoders, ["train", "L1"]) == []


def test_the_figure_marks_a_measured_zero_with_a_dot_and_a_missing_cell_with_nothing(tmp_path, monkeypatch):
  figures = []
  monkeypatch.setattr(plots.fileio, "save_figure", lambda fig, path, **kw: figures.append(fig) or path)
  values = {("place", "ae", "train"): (0.0, 0.0, 0.0), ("place", "ae", "L1"): (0.25, 0.1, 0.4),
            ("place", "savi", "L1"): (0.0, 0.0, 0.05)}                 # place x SAVi has no train-level cell
  plots.levels_with_intervals(values, ["place"], ["ae", "savi"], ["train", "L1"], str(tmp_path / "f.png"))
  (ax,) = figures[0].axes
  dots = {line.get_color(): list(zip(line.get_xdata(), line.get_ydata())) for line in ax.get_lines()
          if line.get_marker() == "o"}
  # bars of width 0.4 at -0.2 (AE, colour C0: its index among the encoders given) and +0.2 (SAVi, C1) of each
  # level's tick: AE's 0 at train, SAVi's at L1; none for AE's 0.25 nor for SAVi's missing train cell
  assert dots == {"C0": [(pytest.approx(-0.2), plots.ZERO_DOT)], "C1": [(pytest.approx(1.2), plots.ZERO_DOT)]}
