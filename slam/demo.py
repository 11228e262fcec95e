"""The built-in demo: a synthetic loop sequence generated once into a cache folder."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from slam.data.synthetic import SynthConfig, generate_sequence

log = logging.getLogger(__name__)

#: Bump when the generator's output changes so stale caches are regenerated.
DEMO_VERSION = 1
DEMO_CONFIG = SynthConfig(frames=300, loop=True, seed=0)


def cache_dir() -> Path:
    """``$SLAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/rgbd-slam``, else ``~/.cache/rgbd-slam``."""
    env = os.environ.get("SLAM_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rgbd-slam"


def demo_sequence_path() -> Path:
    """Path of the demo sequence, generating it on first use (about half a minute)."""
    path = cache_dir() / f"demo-v{DEMO_VERSION}"
    if not (path / ".complete").is_file():
        log.info("generating the synthetic demo sequence into %s", path)
        generate_sequence(path, DEMO_CONFIG)
    return path
