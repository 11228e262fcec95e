"""Writing a run folder: :func:`save_run` (the results of :func:`slam.run`) and
:func:`write_config` (``config.yaml``, written before the first frame). Every file is written
atomically, ``metrics.json`` last."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from slam.errors import RunFolderError
from slam.run_folder.layout import (
    CONFIG_FILE,
    LOOPS_FILE,
    MAP_DIR,
    MESH_FILE,
    METRICS_FILE,
    ODOMETRY_FILE,
    POSE_GRAPH_FILE,
    TRACKING_FILE,
    TRAJECTORY_FILE,
    segment_file,
)
from slam.run_folder.provenance import software, software_line
from slam.run_folder.tracking_csv import format_rows
from slam.trajectory import atomic_write_text, write_tum

if TYPE_CHECKING:
    from slam.config import SlamConfig
    from slam.results import RunResult

__all__ = ["save_run", "write_config"]

log = logging.getLogger(__name__)


def write_config(run_dir: str | Path, config: SlamConfig) -> Path:
    """Write the run's ``config.yaml`` (the full configuration; ``slam run --config`` reads it
    back), headed by a comment naming the software that ran it (version, git commit); returns
    its path."""
    path = Path(run_dir) / CONFIG_FILE
    header = (
        f"# written by {software_line()}\n"
        f"# the full configuration of this run: `slam run SEQUENCE --config {CONFIG_FILE}` runs "
        "it again\n"
    )
    atomic_write_text(path, header + config.to_yaml())
    return path


def save_run(result: RunResult, out_dir: str | Path, overwrite: bool = False) -> Path:
    """Write the run folder: trajectory.txt, odometry.txt, mesh.ply, config.yaml, tracking.csv,
    pose_graph.g2o, loops.json, segment_N.txt (map segments never joined to the main one), map/
    (the keyframes and TSDF a later run can localise in: :mod:`slam.saved_map`) and,
    last, metrics.json, which marks the folder as holding a complete run, with the version and
    git commit of the software (``result.metrics`` gets them too). A folder that already holds
    a complete run is refused unless ``overwrite``. Every file is written atomically."""
    out = Path(out_dir)
    if (out / METRICS_FILE).is_file() and not overwrite:
        raise RunFolderError(
            f"{out} already holds a complete run ({METRICS_FILE}); pass overwrite=True to "
            "replace it, or save into another folder"
        )
    try:
        _write_all(result, out)
    except OSError as exc:
        raise RunFolderError(
            f"{out}: the run's results could not be written ({exc}); no {METRICS_FILE} was "
            "written, so the folder does not pass for a complete run: free space, then run "
            "again (or `slam run --resume` when the run has a checkpoint)"
        ) from exc
    return out


def _write_all(result: RunResult, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / METRICS_FILE).unlink(missing_ok=True)
    write_tum(out / TRAJECTORY_FILE, result.trajectory)
    write_tum(out / ODOMETRY_FILE, result.odometry)
    for seg, traj in result.segments.items():
        write_tum(out / segment_file(seg), traj)
    if result.mesh is not None and len(result.mesh.vertices) > 0:
        from slam.mapping.tsdf import write_mesh

        write_mesh(out / MESH_FILE, result.mesh)
    elif result.mesh is not None:
        log.warning(
            "%s: the map is empty (no surface seen with enough weight); no %s", out, MESH_FILE
        )
    if result.config is not None:
        write_config(out, result.config)
    if result.tracking and (result.config is None or result.config.output.save_tracking_log):
        atomic_write_text(out / TRACKING_FILE, format_rows(result.tracking))
    if result.loop_closer is not None:
        result.loop_closer.graph.write_g2o(out / POSE_GRAPH_FILE)
        loops = json.dumps(result.loop_closer.loops_json(), indent=1) + "\n"
        atomic_write_text(out / LOOPS_FILE, loops)
    if result.map is not None:
        from slam.config import SlamConfig

        result.map.save(out / MAP_DIR, result.config or SlamConfig())
    result.metrics.update(software())
    atomic_write_text(out / METRICS_FILE, json.dumps(result.metrics.as_json(), indent=2) + "\n")
