"""The package's run-time imports: scikit-learn, SUMO and the tests stay out of it (SUMO's
programs are looked up only when the SUMO source simulates)."""

import subprocess
import sys
from pathlib import Path

from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[1]

_IMPORT_ALL = """
import importlib, pkgutil, sys
import cvmdx_jax
names = [m.name for m in pkgutil.walk_packages(cvmdx_jax.__path__, "cvmdx_jax.")]
for name in names:
  importlib.import_module(name)
assert "cvmdx_jax.evaluation.report" in names
print(sorted({n.split(".")[0] for n in sys.modules
              if n.split(".")[0] in ("sklearn", "sumo", "sumolib", "tests")}))
"""


def test_no_module_of_the_package_imports_sklearn_sumo_or_tests():
  env = environ(JAX_PLATFORMS="cpu")
  proc = subprocess.run(
      [sys.executable, "-c", _IMPORT_ALL],
      cwd=REPO,
      env=env,
      capture_output=True,
      text=True,
      timeout=600,
  )
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert proc.stdout.strip().splitlines()[-1] == "[]"


def _package_imports() -> dict[str, set[str]]:
  """{module: the cvmdx_jax modules it imports at module level} from the source (AST)."""
  import ast

  root = REPO / "cvmdx_jax"
  modules = {
      ".".join(p.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"): p
      for p in root.rglob("*.py")
  }
  graph = {}
  for name, path in modules.items():
    deps = set()
    for node in ast.parse(path.read_text()).body:  # module level only
      if isinstance(node, ast.Import):
        deps |= {a.name for a in node.names}
      elif isinstance(node, ast.ImportFrom) and node.module:
        deps |= {
            f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
            for a in node.names
        }
    graph[name] = {d for d in deps if d in modules and d != name}
  return graph


def test_no_import_cycles_and_at_most_ten_top_level_modules():
  graph = _package_imports()
  state = {}  # module -> "open" while on the DFS stack, "done" after

  def visit(name, stack):
    state[name] = "open"
    for dep in sorted(graph[name]):
      assert state.get(dep) != "open", f"import cycle: {' -> '.join([*stack, name, dep])}"
      if dep not in state:
        visit(dep, [*stack, name])
    state[name] = "done"

  for name in sorted(graph):
    if name not in state:
      visit(name, [])
  top = sorted(p.name for p in (REPO / "cvmdx_jax").glob("*.py"))
  assert len(top) <= 10, top
  assert "cvmdx_jax.runs.loaders" in graph and "cvmdx_jax.storage.identity" in graph


def _package_of(module: str) -> str:
  """cvmdx_jax.runs.layout -> runs; a top-level module is its own package."""
  return module.split(".")[1]


def test_no_package_imports_one_that_imports_it_back():
  """The packages form layers: no import runs back up, so no two packages import each
  other, directly or round a longer loop. A failure names the module-level imports that
  close each loop."""
  modules = _package_imports()
  graph = {}
  for name, deps in modules.items():
    for dep in deps:
      if _package_of(dep) != _package_of(name):
        graph.setdefault(_package_of(name), set()).add(_package_of(dep))

  def reachable(start):
    seen, todo = set(), [start]
    while todo:
      for nxt in graph.get(todo.pop(), ()):
        if nxt not in seen:
          seen.add(nxt)
          todo.append(nxt)
    return seen

  loops = sorted(
      f"{name} -> {dep}"
      for name, deps in modules.items()
      for dep in deps
      if _package_of(dep) != _package_of(name) and _package_of(name) in reachable(_package_of(dep))
  )
  assert loops == []


def test_the_configs_sit_below_every_package_that_uses_them():
  """cvmdx_jax.config imports only the constants, the ego-motion features and the error
  base class, so models, samplers, trainers and loaders can all import their configs."""
  graph = _package_imports()
  used = {
      dep
      for name, deps in graph.items()
      if name.startswith("cvmdx_jax.config.")
      for dep in deps
      if not dep.startswith("cvmdx_jax.config")
  }
  assert used <= {"cvmdx_jax.constants", "cvmdx_jax.ego_motion", "cvmdx_jax.errors"}, used
