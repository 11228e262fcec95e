"""Reading a run folder: :class:`RunFolder`, the one reader of what ``slam run`` writes, used by
``slam eval``, ``slam report``, ``slam view`` and ``render_run``.

Each accessor reads its file when called (nothing is cached) and says what is wrong with a
missing or malformed file: optional files give ``None`` (or ``{}``) when absent, a present file
that cannot be read is a :class:`~slam.errors.RunFolderError` (a ``config.yaml`` that is not a
valid configuration, a :class:`~slam.errors.ConfigError`; a bad trajectory, a
:class:`~slam.errors.TrajectoryError`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slam.errors import ConfigError, RunFolderError, TrajectoryError
from slam.run_folder.layout import (
    CONFIG_FILE,
    LOOPS_FILE,
    MESH_FILE,
    METRICS_FILE,
    ODOMETRY_FILE,
    SEGMENT_GLOB,
    TRACKING_FILE,
    TRAJECTORY_FILE,
    segment_number,
)
from slam.run_folder.tracking_csv import read_tracking_csv
from slam.trajectory import Trajectory, read_tum

if TYPE_CHECKING:
    import open3d as o3d

    from slam.config import SlamConfig
    from slam.mapping.ply import PlyHeader
    from slam.records import TrackingStatus

__all__ = ["RunFolder", "same_trajectory"]


def same_trajectory(a: Trajectory, b: Trajectory) -> bool:
    """Whether two trajectories hold exactly the same timestamps and poses."""
    return (
        len(a) == len(b)
        and bool(np.array_equal(a.timestamps, b.timestamps))
        and bool(np.array_equal(a.poses, b.poses))
    )


#: The fields of a ``loops.json`` candidate (:meth:`slam.records.LoopRecord.as_json`) that
#: readers use, and their JSON types (bool is not a number here).
_LOOP_FIELDS: dict[str, tuple[type, ...]] = {
    **dict.fromkeys(("query_kf", "match_kf", "query_frame", "match_frame"), (int,)),
    **dict.fromkeys(("matches", "inliers"), (int,)),
    **dict.fromkeys(
        ("query_timestamp", "match_timestamp", "score", "inlier_ratio", "icp_fitness", "overlap"),
        (int, float),
    ),
    "accepted": (bool,),
    "reason": (str,),
}
_WANT = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string"}


def _loop_candidate_problem(c: Any) -> str | None:
    """What is wrong with one ``loops.json`` candidate (``None``: nothing): not an object, a
    field of the wrong type or a non-finite number, a ``T_match_query`` that is not 4x4."""
    if not isinstance(c, dict):
        return f"expected an object, got {type(c).__name__} {str(c)[:60]!r}"
    for key, types_ in _LOOP_FIELDS.items():
        if key not in c:
            continue
        v = c[key]
        wrong = not isinstance(v, types_) or (isinstance(v, bool) and bool not in types_)
        if wrong or (isinstance(v, float) and not math.isfinite(v)):
            return f"'{key}' must be {_WANT[types_[-1]]}, got {v!r}"
    if "T_match_query" in c:
        T = c["T_match_query"]
        ok = isinstance(T, list) and len(T) == 4
        ok = ok and all(isinstance(r, list) and len(r) == 4 for r in T)
        ok = ok and all(
            isinstance(x, int | float) and not isinstance(x, bool) for r in T for x in r
        )
        if not ok:
            return f"'T_match_query' must be a 4x4 list of numbers, got {str(T)[:80]}"
    return None


class RunFolder:
    """A run folder written by ``slam run`` (see :mod:`slam.run_folder`), opened on its path."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __fspath__(self) -> str:
        return str(self.path)

    # --- files
    def file(self, name: str) -> Path:
        """The path of ``name`` (one of the :mod:`slam.run_folder.layout` names) in the folder."""
        return self.path / name

    def has(self, name: str) -> bool:
        """Whether the file ``name`` is in the folder."""
        return (self.path / name).is_file()

    @property
    def complete(self) -> bool:
        """Whether the folder holds a complete run (its ``metrics.json`` is written last)."""
        return self.has(METRICS_FILE)

    def require_complete(self) -> RunFolder:
        """This folder if it holds a complete run, else a :class:`RunFolderError` saying what
        is there instead (see :func:`slam.run_folder.require_complete`)."""
        from slam.run_folder import require_complete

        require_complete(self.path)
        return self

    # --- contents
    def _json(self, name: str) -> Any:
        path = self.file(name)
        try:
            return json.loads(path.read_text())
        except OSError as exc:
            raise RunFolderError(f"{path}: cannot read: {exc}") from exc
        except ValueError as exc:
            raise RunFolderError(
                f"{path}: not valid JSON ({exc}); was the run interrupted while writing it?"
            ) from exc
        except RecursionError:  # arrays nested thousands deep: no file this package writes
            raise RunFolderError(
                f"{path}: nested too deeply to be a file of `slam run`; was it replaced?"
            ) from None

    def metrics(self) -> dict[str, Any]:
        """``metrics.json`` (``{}`` when absent or not an object)."""
        if not self.has(METRICS_FILE):
            return {}
        data = self._json(METRICS_FILE)
        return data if isinstance(data, dict) else {}

    def config(self) -> SlamConfig | None:
        """``config.yaml`` through :func:`slam.config.load_config` (``None`` when absent)."""
        from slam.config import load_config

        return load_config(self.file(CONFIG_FILE)) if self.has(CONFIG_FILE) else None

    def trajectory(self) -> Trajectory:
        """``trajectory.txt``, the final trajectory; a :class:`TrajectoryError` when missing."""
        if not self.has(TRAJECTORY_FILE):
            raise TrajectoryError(
                f"{self.path}: no {TRAJECTORY_FILE} in the run folder (is it the --out folder "
                "of `slam run`?)"
            )
        return read_tum(self.file(TRAJECTORY_FILE))

    def odometry(self) -> Trajectory | None:
        """``odometry.txt``, the trajectory before loop closure (``None`` when absent)."""
        return read_tum(self.file(ODOMETRY_FILE)) if self.has(ODOMETRY_FILE) else None

    def segments(self) -> dict[int, Trajectory]:
        """The ``segment_N.txt`` trajectories (map segments never joined), by segment number."""
        out = {}
        for path in sorted(self.path.glob(SEGMENT_GLOB)):
            seg = segment_number(path.name)
            if seg is not None and path.is_file():
                out[seg] = read_tum(path)
        return dict(sorted(out.items()))

    def tracking(self) -> list[TrackingStatus] | None:
        """``tracking.csv`` as its :class:`~slam.records.TrackingStatus` records (``None`` when
        absent: the run had ``output.save_tracking_log`` off)."""
        return read_tracking_csv(self.file(TRACKING_FILE)) if self.has(TRACKING_FILE) else None

    def loops(self) -> list[dict[str, Any]] | None:
        """The loop candidates of ``loops.json`` (its ``candidates`` list: the records of
        :class:`slam.loops.closer.LoopCloser`), ``None`` when absent (no loop closure)."""
        if not self.has(LOOPS_FILE):
            return None
        data = self._json(LOOPS_FILE)
        cands = data.get("candidates") if isinstance(data, dict) else None
        if not isinstance(cands, list):
            raise RunFolderError(
                f"{self.file(LOOPS_FILE)}: expected an object with a 'candidates' list, "
                f"got {type(data).__name__}"
            )
        for k, c in enumerate(cands):
            problem = _loop_candidate_problem(c)
            if problem is not None:
                raise RunFolderError(
                    f"{self.file(LOOPS_FILE)}: loop candidate {k} (of {len(cands)}) is damaged: "
                    f"{problem}; restore the file from the run, or delete it to go on without "
                    "the loop details"
                )
        return list(cands)

    def accepted_loops(self) -> list[dict[str, Any]]:
        """The accepted loop candidates (``[]`` without ``loops.json``)."""
        return [c for c in self.loops() or [] if c.get("accepted")]

    def mesh_path(self) -> Path | None:
        """``mesh.ply`` (``None`` when absent: an empty map, or ``output.save_mesh`` off)."""
        return self.file(MESH_FILE) if self.has(MESH_FILE) else None

    def mesh(self) -> o3d.geometry.TriangleMesh | None:
        """``mesh.ply`` read (``None`` when absent); a RunFolderError when the file is cut
        short or its header declares more than it holds."""
        path = self.mesh_path()
        if path is None:
            return None
        import open3d as o3d

        header = _mesh_header(path)
        mesh = o3d.io.read_triangle_mesh(str(path))
        got = (len(mesh.vertices), len(mesh.triangles))
        want = (header.count("vertex"), header.count("face"))
        if got != want:
            raise RunFolderError(
                f"{path}: {got[0]} vertices and {got[1]} triangles read where its header declares "
                f"{want[0]} and {want[1]}: cut short or damaged; run `slam run` again to write it"
            )
        return mesh

    def sequence_path(self) -> str | None:
        """The sequence folder the run was made from, as recorded: ``dataset.path`` of
        ``config.yaml``, else ``sequence`` of ``metrics.json`` (``None`` when neither names it;
        an unreadable ``metrics.json`` counts as naming none)."""
        try:
            cfg = self.config()
        except ConfigError:  # a config of another version: the metrics still name the folder
            cfg = None
        if cfg is not None and cfg.dataset.path:
            return cfg.dataset.path
        return self.recorded_sequence()

    def recorded_sequence(self) -> str | None:
        """``sequence`` of ``metrics.json`` (``None`` when absent or unreadable)."""
        try:
            seq = self.metrics().get("sequence")
        except RunFolderError:
            return None
        return str(seq) if seq else None

    def sequence_dir(self) -> Path | None:
        """:meth:`sequence_path` as an existing folder: as recorded (a relative path: to the
        working directory, then to the run folder); ``None`` when there is none."""
        recorded = self.sequence_path()
        if not recorded:
            return None
        candidates = [Path(recorded).expanduser()]
        if not candidates[0].is_absolute():
            candidates.append(self.path / recorded)
        return next((c for c in candidates if c.is_dir()), None)


def _mesh_header(path: Path) -> PlyHeader:
    """The header of the mesh at ``path``, refused when the file holds fewer bytes than it
    declares (a RunFolderError)."""
    from slam.mapping.ply import read_ply_header

    advice = "run `slam run` again to write it"
    try:
        header = read_ply_header(path)
    except (OSError, ValueError) as exc:
        raise RunFolderError(f"{path}: {exc}; {advice}") from exc
    size = path.stat().st_size
    if header.least_bytes() > size:
        counts = ", ".join(f"{e.count} {e.name}" for e in header.elements)
        raise RunFolderError(
            f"{path}: its header declares {counts}, at least {header.least_bytes()} bytes, but "
            f"the file has {size}: cut short or damaged; {advice}"
        )
    return header
