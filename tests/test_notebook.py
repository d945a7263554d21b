"""notebooks/inspect_run.ipynb, run top to bottom on the tiny run (nbclient), and roboshape as an installed package."""
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(ROOT, "notebooks", "inspect_run.ipynb")
# Appended to the notebook here: what its cells computed, for the assertions below.
PROBE = ('import json\n'
         'print(json.dumps(dict(result=result, frames=frames.shape, tokens=tokens.shape, panels=panels.shape)))')


def test_roboshape_imports_from_any_folder(tmp_path):
  """`make setup` installs this checkout into .venv (editable): roboshape and configs import outside the
  repository, without PYTHONPATH, as the code here."""
  env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
  out = subprocess.run([sys.executable, "-c", "import configs, roboshape; print(roboshape.__file__)"], cwd=tmp_path,
                       env=env, capture_output=True, text=True, timeout=120, check=False)
  assert out.returncode == 0, f"run `make setup` (it installs roboshape into .venv): {out.stderr.strip()[-300:]}"
  assert os.path.realpath(out.stdout.strip()) == os.path.realpath(os.path.join(ROOT, "roboshape", "__init__.py"))


def _outputs(cell, kind):
  return [o for o in cell.outputs if kind in o.get("data", {})]


def test_the_notebook_runs_on_the_tiny_run_from_another_folder(tiny_run, tmp_path, monkeypatch):
  import nbclient  # pylint: disable=import-outside-toplevel
  import nbformat  # pylint: disable=import-outside-toplevel
  notebook = nbformat.read(NOTEBOOK, as_version=4)
  code = [cell for cell in notebook.cells if cell.cell_type == "code"]
  assert code and not any(cell.outputs or cell.execution_count for cell in code)   # committed without outputs
  notebook.cells.append(nbformat.v4.new_code_cell(PROBE))
  monkeypatch.setenv("ROBOSHAPE_WORKDIR", tiny_run)
  monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p))
  monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")     # compile-bound, as the run it inspects
  nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                          resources={"metadata": {"path": str(tmp_path)}}).execute()
  seen = json.loads(notebook.cells[-1].outputs[-1]["text"])
  with open(os.path.join(tiny_run, "eval", "results.json")) as f:
    logged = json.load(f)["rollouts"][0]                      # the evaluate stage's first rollout: the same seed
  assert [seen["result"][k] for k in ("success", "length", "ended")] == [logged[k] for k in ("success", "length",
                                                                                             "ended")]
  steps = logged["length"] + 1
  assert seen["frames"] == [steps, 16, 16, 3]
  assert seen["tokens"][0] == steps and seen["panels"][:2] == [steps, 16]     # a token set and a panel per frame
  with open(os.path.join(tiny_run, "eval", "table.md")) as f:
    table = f.read()
  assert [o["data"]["text/markdown"] for cell in code for o in _outputs(cell, "text/markdown")] == [table]
  assert sum(len(_outputs(cell, "image/png")) for cell in code) == 4   # two curves, the rollout, its slots
