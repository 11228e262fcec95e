"""Issue 19, item 15: the README's quick start names commands and options that exist (each
was run by hand on tum-fr1-xyz with --max-frames 60; this keeps the text from going stale)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from typer.testing import CliRunner

from slam.cli import app

ROOT = Path(__file__).resolve().parents[1]


def _quick_start() -> list[list[str]]:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("**Quick start**")
    assert start < readme.index("## "), "the quick start is near the top, before any section"
    block = re.search(r"```bash\n(.*?)```", readme[start:], re.S)
    assert block is not None
    return [shlex.split(line, comments=True) for line in block.group(1).splitlines() if line]


def test_quick_start_commands_exist():
    lines = _quick_start()
    assert len(lines) == 5
    slam_cmds = [ln for ln in lines if ln[0] == "slam"]
    assert [c[1] for c in slam_cmds] == ["run", "eval", "report"]
    runner = CliRunner()
    for cmd in slam_cmds:
        res = runner.invoke(app, [cmd[1], "--help"])
        assert res.exit_code == 0, res.output
        for opt in (a for a in cmd[2:] if a.startswith("--")):
            assert opt in res.output, f"`slam {cmd[1]}` has no {opt}"
    assert "--max-frames" in runner.invoke(app, ["run", "--help"]).output
    (script,) = [ln for ln in lines if ln[0] == "python"]
    assert (ROOT / script[1]).is_file()
    # one run folder flows through all of them
    run_dir = slam_cmds[0][slam_cmds[0].index("--out") + 1]
    assert all(run_dir in c for c in slam_cmds[1:]) and run_dir in script
