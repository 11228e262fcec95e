"""High-level entry points used by the CLI and by scripts."""

from __future__ import annotations

import logging
from pathlib import Path

from slam.config import SlamConfig, load_config
from slam.data.base import Sequence
from slam.data.loader import open_sequence
from slam.pipeline import ProgressCallback, RunResult, run, save_run

log = logging.getLogger(__name__)


def run_sequence(
    sequence: str | Path | None,
    out_dir: str | Path,
    config_path: str | Path | None = None,
    config: SlamConfig | None = None,
    max_frames: int | None = None,
    progress: ProgressCallback | None = None,
) -> tuple[RunResult, Path]:
    """Open a sequence folder (``None``: the built-in synthetic demo), run SLAM, save the run
    folder. Config: ``config`` if given, else defaults overridden by the YAML at ``config_path``.
    """
    cfg = config if config is not None else load_config(config_path)
    if sequence is None:
        from slam.demo import demo_sequence_path

        sequence = demo_sequence_path()
    if max_frames is not None:
        cfg.dataset.max_frames = max_frames
    cfg.dataset.path = str(Path(sequence).resolve())
    seq: Sequence = open_sequence(sequence, cfg.dataset.layout, cfg.dataset.calibration)
    result = run(seq, cfg, progress=progress)
    return result, save_run(result, out_dir)
