"""The names of everything a run folder holds: the one place they are spelled.

Every module that reads or writes a run folder uses these constants (``slam run`` writes the
results, ``slam report`` and ``slam view`` add theirs); :mod:`slam.run_folder` re-exports them.
"""

from __future__ import annotations

#: ``metrics.json``: the run's numbers; written last, its presence marks a complete run.
METRICS_FILE = "metrics.json"
#: The final trajectory (after loop closure), TUM format.
TRAJECTORY_FILE = "trajectory.txt"
#: The frontend's trajectory (before loop closure), TUM format.
ODOMETRY_FILE = "odometry.txt"
#: The map's surface.
MESH_FILE = "mesh.ply"
#: The full configuration of the run (written before the first frame).
CONFIG_FILE = "config.yaml"
#: One row per frame: :class:`slam.records.TrackingStatus` (see :mod:`slam.run_folder.tracking_csv`).
TRACKING_FILE = "tracking.csv"
#: Loop candidates and their verification.
LOOPS_FILE = "loops.json"
#: The pose graph (g2o text format).
POSE_GRAPH_FILE = "pose_graph.g2o"
#: ``slam report``: the report and its plots.
REPORT_FILE = "report.md"
TOPVIEW_PNG = "report_topview.png"
ERROR_PNG = "report_error.png"
TIMING_PNG = "report_timing.png"
REPORT_PNG_GLOB = "report_*.png"
#: ``slam view`` (and the default of ``slam run --rerun``): the rerun recording.
RECORDING_FILE = "recording.rrd"
#: ``slam run --workers N``: the chunks, how each joined the one before it, worker times.
CHUNKS_FILE = "chunks.json"
#: Map segments never joined to the main one: ``segment_N.txt`` (:func:`segment_file`).
SEGMENT_PREFIX = "segment_"
SEGMENT_SUFFIX = ".txt"
SEGMENT_GLOB = f"{SEGMENT_PREFIX}*{SEGMENT_SUFFIX}"
#: Working folders of a run in progress (removed once the results are written).
MAP_DIR = "map"  # the map a later run localises in (slam.saved_map)
CHECKPOINT_DIR = "checkpoint"
SUBMAPS_DIR = "submaps"
#: ``slam run --workers N``: one folder per chunk (its state and submaps) until the join is done
CHUNKS_DIR = "chunks"
#: Held by the process writing the folder (slam.run_folder.lock); not an output.
LOCK_FILE = ".lock"

#: Files a run writes (and ``slam report`` / ``slam view`` add); their presence means the
#: folder holds a run.
RUN_FILES = (
    METRICS_FILE,
    TRAJECTORY_FILE,
    ODOMETRY_FILE,
    MESH_FILE,
    CONFIG_FILE,
    TRACKING_FILE,
    LOOPS_FILE,
    POSE_GRAPH_FILE,
    REPORT_FILE,
    RECORDING_FILE,
    CHUNKS_FILE,
)
RUN_GLOBS = (REPORT_PNG_GLOB, SEGMENT_GLOB)
WORK_DIRS = (CHECKPOINT_DIR, SUBMAPS_DIR, CHUNKS_DIR)
OUTPUT_DIRS = (MAP_DIR,)


def segment_file(segment: int) -> str:
    """The file name of map segment ``segment``'s trajectory."""
    return f"{SEGMENT_PREFIX}{segment}{SEGMENT_SUFFIX}"


def segment_number(name: str) -> int | None:
    """The segment number of a ``segment_N.txt`` file name, else ``None``."""
    if not (name.startswith(SEGMENT_PREFIX) and name.endswith(SEGMENT_SUFFIX)):
        return None
    digits = name[len(SEGMENT_PREFIX) : -len(SEGMENT_SUFFIX)]
    return int(digits) if digits.isdigit() else None
