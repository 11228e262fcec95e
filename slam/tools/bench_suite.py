"""Benchmark suites (:mod:`slam.tools.bench`): the suite YAML parsed into sequences x
configurations."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slam.config import read_yaml
from slam.errors import ConfigError

__all__ = ["DEMO", "Suite", "SuiteSequence", "load_suite", "suite_from_dict"]

#: The suite entry naming the built-in synthetic demo.
DEMO = "demo"


@dataclass
class SuiteSequence:
    name: str
    path: str  # a folder, or "demo"
    max_frames: int | None = None


@dataclass
class Suite:
    """A parsed suite: ``configs`` maps a name to config overrides (a nested dict) or to the path
    of a YAML config file."""

    name: str
    sequences: list[SuiteSequence]
    configs: dict[str, dict[str, Any] | str] = field(default_factory=lambda: {"default": {}})
    max_frames: int | None = None
    base_dir: Path = field(default_factory=Path.cwd)


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("_") or "run"


def _max_frames(value: Any, where: str) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{where}: max_frames must be a positive integer, got {value!r}")
    return value


def suite_from_dict(data: Any, base_dir: str | Path = ".", name: str = "suite") -> Suite:
    """Parse a suite mapping (the YAML's content). Relative paths are relative to ``base_dir``.
    Raises :class:`ConfigError` on a malformed suite (runs are not checked here)."""
    if not isinstance(data, dict):
        raise ConfigError(f"suite {name}: expected a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - {"name", "max_frames", "sequences", "configs"})
    if unknown:
        raise ConfigError(
            f"suite {name}: unknown key(s) {unknown}; valid: name, max_frames, sequences, configs"
        )
    name = str(data.get("name") or name)
    raw_seqs = data.get("sequences")
    if not isinstance(raw_seqs, list) or not raw_seqs:
        raise ConfigError(
            f"suite {name}: 'sequences' must be a non-empty list of paths (or 'demo', or "
            f"{{name, path, max_frames}} mappings)"
        )
    seqs: list[SuiteSequence] = []
    for i, s in enumerate(raw_seqs):
        where = f"suite {name}, sequences[{i}]"
        if isinstance(s, str):
            path, seq_name, mf = s, None, None
        elif isinstance(s, dict) and isinstance(s.get("path"), str):
            bad = sorted(set(s) - {"name", "path", "max_frames"})
            if bad:
                raise ConfigError(f"{where}: unknown key(s) {bad}; valid: name, path, max_frames")
            path, seq_name = s["path"], s.get("name")
            mf = _max_frames(s.get("max_frames"), where)
        else:
            raise ConfigError(f"{where}: expected a path or a mapping with 'path', got {s!r}")
        if seq_name is None:
            seq_name = DEMO if path == DEMO else Path(path).name or path
        seqs.append(SuiteSequence(_safe_name(seq_name), path, mf))
    names = [s.name for s in seqs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"suite {name}: duplicate sequence name(s) {dup}; give each a 'name'")
    raw_cfgs = data.get("configs")
    if raw_cfgs is None:
        raw_cfgs = {"default": {}}
    if not isinstance(raw_cfgs, dict) or not raw_cfgs:
        raise ConfigError(
            f"suite {name}: 'configs' must map a name to config overrides or a YAML file path"
        )
    configs: dict[str, dict[str, Any] | str] = {}
    for cname, c in raw_cfgs.items():
        if c is None:
            c = {}
        if not isinstance(c, (dict, str)):
            raise ConfigError(
                f"suite {name}, configs.{cname}: expected overrides (a mapping) or a YAML file "
                f"path, got {c!r}"
            )
        configs[_safe_name(cname)] = c
    return Suite(
        name=_safe_name(name),
        sequences=seqs,
        configs=configs,
        max_frames=_max_frames(data.get("max_frames"), f"suite {name}"),
        base_dir=Path(base_dir),
    )


def load_suite(path: str | Path) -> Suite:
    """Read a suite YAML file (see the module docstring)."""
    path = Path(path)
    data = read_yaml(path, "the suite")
    return suite_from_dict(data, path.resolve().parent, name=path.stem)
