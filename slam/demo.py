"""The built-in demo: a synthetic loop sequence generated once into a cache folder."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

from slam.synthetic import SynthConfig, generate_sequence

log = logging.getLogger(__name__)

#: Bump when the generator's output changes so stale caches are regenerated.
DEMO_VERSION = 1
DEMO_CONFIG = SynthConfig(frames=300, loop=True, seed=0)
#: Built-in synthetic sequences by name: the demo, and the same loop with a depth distortion
#: that makes odometry drift (~5 deg of heading over the loop) for loop-closure benchmarks.
BUILTIN = {
    "demo": DEMO_CONFIG,
    "demo-drift": SynthConfig(frames=300, loop=True, seed=0, drift_bias=0.006),
}


def cache_dir() -> Path:
    """``$SLAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/rgbd-slam``, else ``~/.cache/rgbd-slam``."""
    env = os.environ.get("SLAM_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rgbd-slam"


def builtin_path(name: str = "demo") -> Path:
    """Where a built-in synthetic sequence (:data:`BUILTIN`) lives in the cache folder."""
    if name not in BUILTIN:
        raise KeyError(f"unknown built-in sequence {name!r}; choose one of {sorted(BUILTIN)}")
    return cache_dir() / f"{name}-v{DEMO_VERSION}"


def is_generated(name: str = "demo") -> bool:
    """True when the built-in sequence is already in the cache (no generation on next use)."""
    return (builtin_path(name) / ".complete").is_file()


def demo_sequence_path(
    name: str = "demo", progress: Callable[[int, int], None] | None = None
) -> Path:
    """Path of a built-in synthetic sequence (:data:`BUILTIN`), generating it into the cache
    folder on first use (about a minute on 2 cores; ``progress(done, total)`` after every
    frame rendered)."""
    path = builtin_path(name)
    if not is_generated(name):
        log.info("generating the synthetic sequence %s into %s", name, path)
        generate_sequence(path, BUILTIN[name], progress=progress)
    return path
