"""The package's floors, read off every module's imports with `ast` (imports inside functions included).

A module may import its own layer or the layers below it, never one above:

  10 benchmarks/, scripts/
  9  stages, status, cli, launch.py, the package's entry points (roboshape/__init__.py), configs/
  8  grid, config_check      the runs of a grid config; the check of a whole config before any stage runs
  7  eval                    the evaluators: closed loop, offline action error, SAVi's and the AE's validation
  6  report                  tables, figures, the verdict, READMEs and publishing, from results files
  5  train                   pretraining, behaviour cloning, the feature cache
  4  encoders                the registry and the frozen encoders it serves
  3  data                    the RLDS dataset
  2  sim, baselines          the simulator bridge; the official R3M / DINO networks
  1  envs, models            the tasks and levels; the Flax modules
  0  errors, fields, fileio, rundir, checkpoint, ranges, progress

no two modules import each other, even through others and even within a layer (an import circle), and no module
reads a private name (a leading underscore) of another module, benchmarks and scripts included.

  python tests/test_layout.py [ROOT]      # prints the arrows that point up, the circles and the private names
"""
import ast
import os
import sys
from typing import Dict, Iterator, List, Optional, Set, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

LAYERS = {
    "roboshape.errors": 0, "roboshape.fields": 0, "roboshape.fileio": 0, "roboshape.rundir": 0,
    "roboshape.checkpoint": 0,
    "roboshape.ranges": 0, "roboshape.progress": 0,
    "roboshape.envs": 1, "roboshape.models": 1,
    "roboshape.sim": 2, "roboshape.baselines": 2,
    "roboshape.data": 3,
    "roboshape.encoders": 4,
    "roboshape.train": 5,
    "roboshape.report": 6,
    "roboshape.eval": 7,
    "roboshape.grid": 8, "roboshape.config_check": 8,
    "roboshape.stages": 9, "roboshape.lanes": 9, "roboshape.status": 9, "roboshape.cli": 9, "roboshape": 9,
    "launch": 9, "configs": 9,
    "benchmarks": 10, "scripts": 10,
}
SCANNED = ("roboshape", "configs", "benchmarks", "scripts", "launch.py")


def layer(module: str) -> Optional[int]:
  """The layer of a dotted module name (its longest prefix in LAYERS); None for a module outside them."""
  parts = module.split(".")
  for n in range(len(parts), 0, -1):
    name = ".".join(parts[:n])
    if name in LAYERS:
      return LAYERS[name]
  return None


def modules(root: str) -> Iterator[Tuple[str, str]]:
  """(dotted name, path) of every Python module under the scanned folders of `root`."""
  for top in SCANNED:
    path = os.path.join(root, top)
    if os.path.isfile(path):
      yield top[:-3], path
      continue
    for folder, dirs, files in os.walk(path):
      dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__")))
      for name in sorted(files):
        if name.endswith(".py"):
          rel = os.path.relpath(os.path.join(folder, name), root)[:-3].split(os.sep)
          if rel[-1] == "__init__":
            rel = rel[:-1]
          yield ".".join(rel), os.path.join(folder, name)


def _resolve(root: str, package: str, name: str) -> str:
  """`from package import name`: the submodule package.name when it exists, else package itself."""
  base = os.path.join(root, *f"{package}.{name}".split("."))
  return f"{package}.{name}" if os.path.isfile(base + ".py") or os.path.isdir(base) else package


def imports(root: str, module: str, path: str) -> Tuple[Set[str], List[str]]:
  """(the first-party modules `module` imports, the private names it takes from other modules)."""
  with open(path) as f:
    tree = ast.parse(f.read(), path)
  found: Set[str] = set()
  private: List[str] = []
  bound: Dict[str, str] = {}                  # local name -> the module it is bound to
  package = module if path.endswith("__init__.py") else module.rpartition(".")[0]
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      for alias in node.names:
        if layer(alias.name) is not None:
          found.add(alias.name)
          if alias.asname:
            bound[alias.asname] = alias.name
    elif isinstance(node, ast.ImportFrom):
      source = node.module or ""
      if node.level:
        parts = package.split(".")[:len(package.split(".")) - node.level + 1]
        source = ".".join(parts + ([source] if source else []))
      if layer(source) is None:
        continue
      for alias in node.names:
        target = _resolve(root, source, alias.name)
        found.add(target)
        if target != source:
          bound[alias.asname or alias.name] = target
        elif alias.name.startswith("_") and source != module:
          private.append(f"{module}: from {source} import {alias.name}")
  for node in ast.walk(tree):
    if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
        and node.attr.startswith("_") and not node.attr.startswith("__") and bound[node.value.id] != module):
      private.append(f"{module}: {bound[node.value.id]}.{node.attr}")
  found.discard(module)
  return found, sorted(set(private))


def scan(root: str) -> Tuple[List[str], List[str]]:
  """(the import arrows under `root` that point to a higher layer, the private names read across modules)."""
  up, private = [], []
  for module, path in modules(root):
    targets, names = imports(root, module, path)
    private += names
    for target in sorted(targets):
      if layer(module) is not None and layer(target) is not None and layer(target) > layer(module):
        up.append(f"{module} (layer {layer(module)}) -> {target} (layer {layer(target)})")
  return up, private


def graph(root: str) -> Dict[str, Set[str]]:
  """Every scanned module under `root` -> the first-party modules it imports."""
  return {module: imports(root, module, path)[0] for module, path in modules(root)}


def _reachable(edges: Dict[str, Set[str]], start: str) -> Set[str]:
  """The modules `start` reaches by one or more imports (itself among them only when it is on a circle)."""
  seen: Set[str] = set()
  todo = list(edges.get(start, ()))
  while todo:
    module = todo.pop()
    if module not in seen:
      seen.add(module)
      todo.extend(edges.get(module, ()))
  return seen


def circles(edges: Dict[str, Set[str]]) -> List[Tuple[str, ...]]:
  """The import circles of a graph: each largest group of modules that all reach one another, sorted."""
  reach = {module: _reachable(edges, module) for module in edges}
  groups = {tuple(sorted(other for other in reach[module] if module in reach[other])) for module in edges}
  return sorted(group for group in groups if group)


def test_no_import_points_to_a_higher_layer():
  up, _ = scan(ROOT)
  assert not up, "imports that point up:\n" + "\n".join(up)


def test_no_modules_import_each_other():
  found = circles(graph(ROOT))
  assert not found, "import circles:\n" + "\n".join(" <-> ".join(group) for group in found)


def test_no_module_reads_another_modules_private_names():
  _, private = scan(ROOT)
  assert not private, "private names read across modules:\n" + "\n".join(private)


def test_train_never_imports_eval_and_the_bottom_imports_nothing_above_it():
  """The two floors the layers exist for, spelled out: train/ -> eval/ and anything below train/ -> train/."""
  for module, path in modules(ROOT):
    targets, _ = imports(ROOT, module, path)
    if module.startswith("roboshape.train"):
      assert not [t for t in targets if t.startswith("roboshape.eval")], module
    if layer(module) is not None and layer(module) < LAYERS["roboshape.train"]:
      assert not [t for t in targets if t.startswith("roboshape.train")], module


def test_reporting_never_imports_evaluation():
  """roboshape/report/ writes tables and figures from results files; the evaluators (roboshape/eval/) write theirs
  through it, never the other way."""
  for module, path in modules(ROOT):
    if module.startswith("roboshape.report"):
      targets, _ = imports(ROOT, module, path)
      assert not [t for t in targets if t.startswith(("roboshape.eval", "roboshape.train"))], module


def test_the_config_check_composes_the_owners_ranges_without_importing_them():
  """roboshape/config_check.py checks the stages' sections through the checks roboshape/stages.py hands it, so it
  imports nothing from the models, the training or the evaluation (inside functions neither)."""
  path = os.path.join(ROOT, "roboshape", "config_check.py")
  targets, _ = imports(ROOT, "roboshape.config_check", path)
  assert "roboshape.ranges" in targets
  assert not [t for t in targets if t.startswith(("roboshape.models", "roboshape.train", "roboshape.eval"))]


def test_the_scan_sees_imports_inside_functions(tmp_path):
  pkg = tmp_path / "roboshape" / "train"
  pkg.mkdir(parents=True)
  (tmp_path / "roboshape" / "__init__.py").write_text("")
  (pkg / "__init__.py").write_text("")
  (pkg / "x.py").write_text("def f():\n  from roboshape.eval import closed_loop\n  from roboshape.data import _y\n")
  up, private = scan(str(tmp_path))
  assert up == ["roboshape.train.x (layer 5) -> roboshape.eval (layer 7)"]
  assert private == ["roboshape.train.x: from roboshape.data import _y"]


def test_a_circle_through_a_third_module_is_found_within_one_layer(tmp_path):
  top = tmp_path / "roboshape"
  top.mkdir()
  (top / "__init__.py").write_text("")
  (top / "stages.py").write_text("from roboshape import lanes\n")
  (top / "lanes.py").write_text("def main():\n  from roboshape import status\n")
  (top / "status.py").write_text("import roboshape.stages\n")
  (top / "cli.py").write_text("from roboshape import stages\n")          # imports the circle, is not on it
  assert circles(graph(str(tmp_path))) == [("roboshape.lanes", "roboshape.stages", "roboshape.status")]
  assert scan(str(tmp_path)) == ([], [])                                  # all layer 9: no arrow points up


if __name__ == "__main__":
  where = sys.argv[1] if len(sys.argv) > 1 else ROOT
  arrows, names = scan(where)
  rings = [" <-> ".join(group) for group in circles(graph(where))]
  print("\n".join(arrows + rings + names))
  print(f"{len(arrows)} import arrows point up; {len(rings)} import circles; {len(names)} private names read across "
        "modules")
