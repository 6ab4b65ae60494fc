"""Every repository path, config preset, dotted name and script flag that the documents
name in code spans exists.

Read without importing the package (no jax): modules are found by file path, names by
`ast`. Each test lists every missing name at once.
"""

import ast
import functools
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "cvmdx_jax"
DOCUMENTS = (
    "README.md",
    "BUILD_NOTES.md",
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md")),
)
TOP_DIRS = ("cvmdx_jax", "experiments", "configs", "tests", "docs")
_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_PATH = re.compile(r"^[\w.-]+(/[\w.-]+)+/?$")
_DOTTED = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)+$")
_FLAG = re.compile(r"--([A-Za-z_][\w.]*)")
_SCRIPT = re.compile(r"experiments/(\w+)\.py")
# config sections named like a package: `train.num_epochs` is a field, `train.loop` a module
_CONFIG_SECTIONS = ("config", "data", "diffusion", "models", "train")
_FILE_SUFFIXES = ("json", "jsonl", "md", "npz", "png", "py", "txt", "csv", "mat", "lock")


def code_texts(markdown: str) -> list[str]:
  """The contents of the fenced blocks and inline code spans of `markdown`."""
  blocks = _FENCE.findall(markdown)
  rest = _FENCE.sub("", markdown)
  return blocks + [m.group(2) for m in _SPAN.finditer(rest)]


def tokens(text: str) -> list[str]:
  """Whitespace-separated words of `text`, shell continuations joined, outer punctuation
  and call arguments stripped."""
  out = []
  for word in text.replace("\\\n", " ").split():
    word = word.strip("\"'(),;[]{}").split("(")[0].rstrip(".,:;")
    if word:
      out.append(word.split("=", 1)[-1] if word.startswith("--") else word)
  return out


def _package_path(parts: list[str]) -> tuple[pathlib.Path | None, list[str]]:
  """The module file that the longest prefix of `parts` names under cvmdx_jax/, and the
  rest of the parts (names inside it); (None, parts) if the first part is no module."""
  here, i = PACKAGE, 0
  while i < len(parts):
    if (here / parts[i]).is_dir():
      here = here / parts[i]
    elif (here / f"{parts[i]}.py").is_file():
      return here / f"{parts[i]}.py", parts[i + 1 :]
    else:
      break
    i += 1
  if i == 0:
    return None, parts
  return here / "__init__.py", parts[i:]


@functools.cache
def _module_names(path: pathlib.Path) -> dict[str, ast.AST | None]:
  """Top-level names of a module: defs, classes, assignments, imports (node or None)."""
  names = {}
  for node in ast.parse(path.read_text()).body:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
      names[node.name] = node
    elif isinstance(node, ast.Assign):
      for target in node.targets:
        if isinstance(target, ast.Name):
          names[target.id] = None
    elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
      names[node.target.id] = None
    elif isinstance(node, (ast.Import, ast.ImportFrom)):
      for alias in node.names:
        names[(alias.asname or alias.name).split(".")[0]] = None
  return names


def _class_names(node: ast.ClassDef) -> set[str]:
  """Names a class body defines: methods, fields, class attributes."""
  names = set()
  for item in node.body:
    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
      names.add(item.name)
    elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
      names.add(item.target.id)
    elif isinstance(item, ast.Assign):
      names.update(t.id for t in item.targets if isinstance(t, ast.Name))
  return names


def dotted_name_missing(name: str) -> bool | None:
  """Whether a dotted name under cvmdx_jax (the prefix optional) is missing; None when
  its first part names no module of the package (a config field, another library)."""
  parts = name.split(".")
  qualified = parts[0] == "cvmdx_jax"
  if qualified:
    parts = parts[1:]
  if parts[-1] in _FILE_SUFFIXES:
    return None
  module, rest = _package_path(parts)
  if module is None:
    return None
  if not module.is_file():
    return True
  if len(parts) == 2 and rest and not qualified and parts[0] in _CONFIG_SECTIONS:
    return None  # `diffusion.class_weights`: a config field, not package.name
  if not rest:
    return False
  names = _module_names(module)
  if rest[0] not in names:
    return True
  node = names[rest[0]]
  if len(rest) > 1 and isinstance(node, ast.ClassDef):
    return rest[1] not in _class_names(node)
  return False


@functools.cache
def presets(config_file: pathlib.Path) -> set[str]:
  """The keywords of `common.parse_arg(arg, ...)` in a configs/ file: its presets."""
  found = set()
  for node in ast.walk(ast.parse(config_file.read_text())):
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "parse_arg"
    ):
      found.update(k.arg for k in node.keywords)
  return found


def path_missing(word: str) -> str | None:
  """Why a repository path word (with an optional `:preset` suffix) is wrong, or None."""
  path, _, preset = word.partition(":")
  if "<" in path or "*" in path or path.startswith("..") or not _PATH.match(path):
    return None
  top = path.split("/")[0]
  if top in TOP_DIRS:
    target = ROOT / path
  elif (PACKAGE / top).is_dir() and path.endswith(".py"):  # runs/demo is no module
    target = PACKAGE / path
  else:
    return None
  if not target.exists():
    return "no such path"
  if preset and top == "configs":
    keys = {p.split("=")[0] for p in re.split(r"[,|]", preset) if p}
    unknown = sorted(keys - presets(target))
    return f"no preset {', '.join(unknown)}" if unknown else None
  return None


@functools.cache
def script_flags(script: pathlib.Path) -> set[str]:
  """Flag names a script defines (absl `flags.DEFINE_*("name", ...)`, config flags, or
  argparse `add_argument("--name", ...)`)."""
  names = {"help", "helpfull", "helpshort"}
  for node in ast.walk(ast.parse(script.read_text())):
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and (node.func.attr.startswith("DEFINE") or node.func.attr == "add_argument")
        and node.args
        and isinstance(node.args[0], ast.Constant)
    ):
      names.add(str(node.args[0].value).removeprefix("--"))
  return names


def flags_missing(text: str) -> list[str]:
  """`--flag`s of an `experiments/*.py` command in `text` that the script does not define."""
  missing = []
  for line in text.replace("\\\n", " ").splitlines():
    line = line.split(" #")[0]  # a shell comment names other programs' flags
    match = _SCRIPT.search(line)
    script = ROOT / "experiments" / f"{match.group(1)}.py" if match else None
    if script is None or not script.is_file():
      continue
    defined = script_flags(script)
    for flag in _FLAG.findall(line[match.end() :]):
      name = flag.split(".")[0]
      if name not in defined:
        missing.append(f"{match.group(0)} --{flag}")
  return missing


def problems(document: str) -> list[str]:
  """Every missing path, preset, dotted name and flag that `document` names."""
  out = []
  for text in code_texts((ROOT / document).read_text()):
    out += [f"{document}: `{f}`: the script defines no such flag" for f in flags_missing(text)]
    for word in tokens(text):
      if "/" in word:
        why = path_missing(word)
        if why:
          out.append(f"{document}: `{word}`: {why}")
      elif _DOTTED.match(word) and dotted_name_missing(word):
        out.append(f"{document}: `{word}`: no such module or name in cvmdx_jax")
  return sorted(set(out))


_MACHINE_PATH = re.compile(r"(?<![\w.<>-])/(tmp|work|home|root|Users)/")


def test_no_document_names_a_machine_or_temporary_path():
  documents = [ROOT / d for d in DOCUMENTS] + sorted((ROOT / "docs").rglob("*.md"))
  found = [
      f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
      for p in dict.fromkeys(documents)
      if p.is_file()
      for i, line in enumerate(p.read_text().splitlines(), 1)
      if _MACHINE_PATH.search(line)
  ]
  assert not found, "machine paths (write them repository-relative):\n" + "\n".join(found)


def test_the_checker_finds_what_is_missing_and_accepts_what_exists():
  assert dotted_name_missing("cvmdx_jax.multimodal.kmeans") is False
  assert dotted_name_missing("storage.identity.check") is False
  assert dotted_name_missing("storage.checkpointing.Checkpoints.load") is False
  assert dotted_name_missing("storage.identity.no_such_function") is True
  assert dotted_name_missing("storage.no_such_module.check") is True
  assert dotted_name_missing("storage.no_such_module") is True
  assert dotted_name_missing("storage.checkpointing.Checkpoints.no_such_method") is True
  assert dotted_name_missing("model.encoder.latent_dim") is None
  assert dotted_name_missing("diffusion.class_weights") is None
  assert dotted_name_missing("cvmdx_jax.diffusion.class_weights") is True
  assert path_missing("cvmdx_jax/multimodal/kmeans.py") is None
  assert path_missing("multimodal/kmeans.py") is None
  assert path_missing("experiments/no_such_script.py") == "no such path"
  assert path_missing("configs/diffusion.py:demo") is None
  assert path_missing("configs/diffusion.py:demo_typo") == "no preset demo_typo"
  assert path_missing("configs/diffusion.py:tiny|demo") is None
  assert path_missing("runs/demo/diffusion") is None
  assert flags_missing("python experiments/train_diffusion.py --workdir=w --config.x=1") == []
  assert flags_missing("experiments/evaluate.py --split=val  # mpirun --allow") == []
  assert flags_missing("experiments/evaluate.py --no_such_flag=1") == [
      "experiments/evaluate.py --no_such_flag"
  ]
  assert code_texts("a `x.y` b\n```\nc d\n```\n") == ["c d\n", "x.y"]
  assert _MACHINE_PATH.search("see /tmp/x/run.log") and _MACHINE_PATH.search("(/work/a)")
  assert not _MACHINE_PATH.search("<scratch>/tmp/x docs/tmp/x ../shared/x")


@pytest.mark.parametrize("document", DOCUMENTS)
def test_every_name_a_document_mentions_exists(document):
  if not (ROOT / document).is_file():
    pytest.skip(f"{document} is not in this checkout")
  found = problems(document)
  assert not found, f"{len(found)} missing:\n" + "\n".join(found)


def test_script_flags_reads_absl_and_argparse_definitions(tmp_path):
  script = tmp_path / "s.py"
  script.write_text(
      'flags.DEFINE_string("workdir", None, "")\n'
      'config_flags.DEFINE_config_file("config")\n'
      'parser.add_argument("--export_dir", required=True)\n'
  )
  assert script_flags(script) >= {"workdir", "config", "export_dir", "help"}
  assert "required" not in script_flags(script)
