"""The package's layering holds (scripts/check_layout.py, described in docs/architecture.md)."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "check_layout.py"


def _load():
    spec = importlib.util.spec_from_file_location("check_layout", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_layout_check_passes_on_the_package():
    out = subprocess.run(
        [sys.executable, str(SCRIPT)], capture_output=True, text=True, cwd=ROOT, check=False
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "layout: 0 problem(s)" in out.stdout


def test_layout_check_sees_an_upward_import_and_a_sibling_import():
    check = _load()
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "from slam.mapping.tsdf import TSDFVolume\n"
        "if TYPE_CHECKING:\n    from slam.system import Slam\n"
        "def f():\n    from slam.tools import eval as e\n"
    )
    found = check.imported_modules(tree)
    assert (2, "slam.mapping.tsdf") in found
    assert all(m != "slam.system" for _, m in found)  # type-checking imports do not run
    assert (6, "slam.tools.eval") in found  # imports in functions do
    frontend, mapping, tools = (
        check._owner(m) for m in ("slam.frontend.icp", "slam.mapping.tsdf", "slam.tools.eval")
    )
    assert frontend[0] == mapping[0] and frontend[1] != mapping[1]
    assert tools[0] > frontend[0]


def test_layout_check_sees_a_run_folder_name_in_code_but_not_in_a_docstring():
    check = _load()
    tree = ast.parse(
        '"""Writes metrics.json."""\nx = run_dir / "metrics.json"\nd = {"submaps": 1}\n'
    )
    docs, parts = check._docstring_nodes(tree), check._path_parts(tree)
    consts = [n for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    assert [id(c) in docs for c in consts] == [True, False, False]
    assert [id(c) in parts for c in consts] == [False, True, False]  # a dict key is no path
