"""Progress bars: tqdm's own on a terminal; a line at most every LOG_INTERVAL seconds in a file."""
import io
import re

from roboshape import progress


class _Terminal(io.StringIO):
  def isatty(self):
    return True


def test_a_bar_written_to_a_file_is_lines_without_carriage_returns_first_and_last_only_in_a_fast_loop():
  out = io.StringIO()
  assert list(progress.bar(range(5), file=out, desc="train_policy")) == [0, 1, 2, 3, 4]
  text = out.getvalue()
  assert "\r" not in text and text.endswith("\n")
  lines = text.splitlines()
  assert len(lines) == 2, lines        # the loop takes far less than LOG_INTERVAL: its start and its end
  assert lines[0].startswith("train_policy:") and "0/5" in lines[0]
  assert "5/5" in lines[1]


def test_a_bar_on_a_file_refreshes_once_the_interval_has_passed(monkeypatch):
  monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)
  out = io.StringIO()
  bar = progress.bar(total=3, file=out, mininterval=0, miniters=1)
  for _ in range(3):
    bar.update(1)
  bar.close()
  counts = re.findall(r"\| (\d/\d) \[", out.getvalue())
  assert counts == ["0/3", "1/3", "2/3", "3/3"] or counts == ["0/3", "1/3", "2/3", "3/3", "3/3"]  # the last
  # again as the bar closes where its rate has changed since


def test_a_redraw_the_same_as_the_line_before_is_left_out():
  out = io.StringIO()
  bar = progress.bar(total=2, file=out, bar_format="{desc} {n}/{total}", desc="evaluate")
  bar.update(2)
  bar.refresh()
  bar.close()
  assert out.getvalue() == "evaluate 0/2\nevaluate 2/2\n"


def test_a_bar_on_a_terminal_is_redrawn_in_place():
  out = _Terminal()
  list(progress.bar(range(3), file=out, mininterval=0, miniters=1))
  assert out.getvalue().count("\r") >= 4
