"""Check the package's layering (docs/architecture.md) and exit non-zero on a violation.

    python scripts/check_layout.py

1. Imports go down the layers, never up (a module may import its own layer and those below);
   ``slam.frontend`` and ``slam.mapping`` share a layer and never import each other. Imports
   under ``if TYPE_CHECKING:`` do not run and are not counted; imports inside functions are.
2. ``import slam`` loads neither Open3D nor GTSAM, and neither does ``import slam.cli``
   (``slam --help``).
3. The run folder's file names are spelled in ``slam/run_folder/`` only (string constants in
   code; docstrings may name them).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "slam"

#: layers, bottom first: a module may import modules of its own layer or of a lower one
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "records",
        (
            "slam.errors",
            "slam.geometry",
            "slam.camera",
            "slam.config",
            "slam.config_ranges",
            "slam.records",
            "slam.keyframe",
            "slam.trajectory",
            "slam.data.layouts",
            "slam.files",
            "slam.run_folder.layout",
        ),
    ),  # fmt: skip
    ("data", ("slam.data",)),
    ("frontend | mapping", ("slam.frontend", "slam.mapping")),
    ("backend", ("slam.backend",)),
    ("loops", ("slam.loops",)),
    (
        "system",
        (
            "slam.system",
            "slam.results",
            "slam.run_metrics",
            "slam.kernels",
            "slam.saved_map",
            "slam.localisation",
            "slam.merge",
        ),
    ),
    ("run folder", ("slam.run_folder",)),
    ("applications", ("slam.pipeline", "slam.api", "slam.chunked", "slam.tools", "slam.synthetic", "slam.demo")),
    ("cli", ("slam.cli", "slam.cli_app", "slam.cli_eval", "slam.__main__", "slam")),
]
#: pairs in one layer that must not import each other
SIBLINGS = [("slam.frontend", "slam.mapping")]
HEAVY = ("open3d", "gtsam")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _owner(module: str) -> tuple[int, str] | None:
    """(layer rank, the prefix that matched) of a ``slam`` module, longest prefix first."""
    best: tuple[int, str] | None = None
    for rank, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (
                best is None or len(p) > len(best[1])
            ):
                best = (rank, p)
    return best


def _type_checking_lines(tree: ast.AST) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                lines.update(range(sub.lineno, (sub.end_lineno or sub.lineno) + 1))
    return lines


def imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every ``slam`` import that runs, including ``from slam import x``
    resolved to ``slam.x`` when ``x`` is a submodule."""
    skip = _type_checking_lines(tree)
    out = []
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("slam")]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("slam"):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                is_module = (PACKAGE.parent / Path(*sub.split("."))).with_suffix(".py").is_file()
                is_package = (PACKAGE.parent / Path(*sub.split("."))).is_dir()
                out.append((node.lineno, sub if is_module or is_package else node.module))
    return out


def check_imports() -> list[str]:
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        me = module_name(path)
        mine = _owner(me)
        if mine is None:
            problems.append(f"{path.relative_to(ROOT)}: module {me} is in no layer of LAYERS")
            continue
        tree = ast.parse(path.read_text(), str(path))
        for line, other in imported_modules(tree):
            theirs = _owner(other)
            if theirs is None or other == "slam":
                continue
            where = f"{path.relative_to(ROOT)}:{line}"
            if theirs[0] > mine[0]:
                problems.append(
                    f"{where}: {me} (layer '{LAYERS[mine[0]][0]}') imports {other} from the "
                    f"higher layer '{LAYERS[theirs[0]][0]}'"
                )
            for a, b in SIBLINGS:
                if {mine[1], theirs[1]} == {a, b}:
                    problems.append(f"{where}: {me} imports {other}: {a} and {b} are siblings")
    return problems


def check_light_import() -> list[str]:
    problems = []
    for stmt in ("import slam", "import slam.cli"):
        code = f"{stmt}, sys; print(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
        out = subprocess.run(
            [sys.executable, "-c", f"import sys; {code}"],
            capture_output=True, text=True, cwd=ROOT, check=False,
        )  # fmt: skip
        if out.returncode != 0:
            problems.append(f"`{stmt}` failed: {out.stderr.strip().splitlines()[-1:]}")
        elif out.stdout.strip():
            problems.append(f"`{stmt}` loads {out.stdout.strip()} (import them where used)")
    return problems


def run_folder_names() -> set[str]:
    sys.path.insert(0, str(ROOT))
    from slam import run_folder

    return set(run_folder.RUN_FILES) | set(run_folder.WORK_DIRS)


def _docstring_nodes(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ids.add(id(body[0].value))
    return ids


def _path_parts(tree: ast.AST) -> set[int]:
    """Constants used as path parts: an operand of ``/`` or a piece of an f-string."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            ids.update(id(x) for x in (node.left, node.right) if isinstance(x, ast.Constant))
        elif isinstance(node, ast.JoinedStr):
            ids.update(id(x) for x in node.values if isinstance(x, ast.Constant))
    return ids


def check_run_folder_names() -> list[str]:
    """File names anywhere in a string constant; folder names (no dot, also ordinary words
    and dict keys) only where used as a path part."""
    names = run_folder_names()
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if (PACKAGE / "run_folder") in path.parents:
            continue
        tree = ast.parse(path.read_text(), str(path))
        docs, parts = _docstring_nodes(tree), _path_parts(tree)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Constant) or not isinstance(node.value, str):
                continue
            if id(node) in docs:
                continue
            for name in names:
                if "." in name:
                    spelled = name in node.value
                else:
                    spelled = id(node) in parts and name in node.value.strip("/").split("/")
                if spelled:
                    problems.append(
                        f"{path.relative_to(ROOT)}:{node.lineno}: run-folder name {name!r} "
                        "spelled outside slam/run_folder (use its constants)"
                    )
    return problems


def main() -> int:
    problems = check_imports() + check_light_import() + check_run_folder_names()
    for p in problems:
        print(p)
    print(f"layout: {len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
