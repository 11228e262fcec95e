"""Which software wrote a run folder: the package version and, when the package runs from a git
checkout, the commit (and whether the checkout had uncommitted changes).

:func:`software` is what ``config.yaml`` (a comment at its top) and ``metrics.json``
(``slam_version``, ``git_commit``, ``git_dirty``) record. Not knowing the commit is never an
error: an installed package, no ``git`` program or an unreadable repository give ``None``.
"""

from __future__ import annotations

import functools
import logging
import os
import subprocess
from pathlib import Path
from typing import Any

import slam

__all__ = ["checkout_root", "git_state", "software", "software_line"]

log = logging.getLogger(__name__)

#: how long a ``git`` call may take before the commit counts as unknown (seconds)
_GIT_TIMEOUT_S = 10.0


def checkout_root() -> Path | None:
    """The git checkout the package runs from (the folder holding ``slam/`` and ``.git``), or
    ``None`` for an installed package."""
    root = Path(slam.__file__).resolve().parents[1]
    return root if (root / ".git").exists() and (root / "pyproject.toml").is_file() else None


def _git(root: Path, *args: str) -> subprocess.CompletedProcess[str] | None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    try:
        return subprocess.run(
            ["git", "--no-optional-locks", "-C", str(root), *args],
            capture_output=True, text=True, timeout=_GIT_TIMEOUT_S, env=env, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError) as exc:
        log.debug("git %s in %s failed: %s", " ".join(args), root, exc)
        return None


@functools.lru_cache(maxsize=1)
def git_state() -> tuple[str | None, bool | None]:
    """(commit, uncommitted changes in tracked files) of the checkout the package runs from;
    ``(None, None)`` when it does not run from one or git cannot tell (read once per process)."""
    root = checkout_root()
    if root is None:
        return None, None
    head = _git(root, "rev-parse", "--verify", "HEAD")
    commit = head.stdout.strip() if head is not None and head.returncode == 0 else ""
    if len(commit) < 40 or any(c not in "0123456789abcdef" for c in commit):
        return None, None
    diff = _git(root, "diff", "--quiet", "HEAD", "--")
    dirty = None if diff is None or diff.returncode not in (0, 1) else diff.returncode == 1
    return commit, dirty


def software() -> dict[str, Any]:
    """``{"slam_version", "git_commit", "git_dirty"}``: the ``metrics.json`` keys."""
    commit, dirty = git_state()
    return {"slam_version": slam.__version__, "git_commit": commit, "git_dirty": dirty}


def software_line() -> str:
    """One line naming the software: ``rgbd-slam 0.1.0 (git commit <sha>, with uncommitted
    changes)``; without a checkout just the version."""
    sw = software()
    text = f"rgbd-slam {sw['slam_version']}"
    if sw["git_commit"] is None:
        return text
    dirty = {True: ", with uncommitted changes", False: "", None: ""}[sw["git_dirty"]]
    return f"{text} (git commit {sw['git_commit']}{dirty})"
