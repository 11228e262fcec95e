"""3D recordings of runs for the rerun viewer (rerun-sdk: the ``viz`` extra, installed from the
checkout with ``pip install -e '.[viz]'``, see :func:`viz_install_hint`).

:class:`RerunRecorder` records a run while it happens (``slam run --rerun FILE.rrd``; its
:meth:`~RerunRecorder.on_frame` is the ``on_frame`` hook of :func:`slam.run`), and
:func:`record_run_folder` makes the same recording from a finished run folder
(``slam view RUN_DIR``). Open a recording with ``rerun FILE.rrd`` (or ``slam view --open``).

Entities (``world`` is the first camera's frame: x right, y down, z forward):

* ``world/camera``: the frame's pose as tracked (odometry, before loop closure), with
  ``world/camera/image`` (pinhole, intrinsics scaled to the logged images), ``.../rgb`` (JPEG)
  and ``.../depth`` (millimetres), downsampled ``image_scale`` times
* ``world/odometry/NNN``: the tracked trajectory so far (in blocks of 100 poses; a strip ends
  where tracking was lost), ``world/keyframes``: keyframe positions so far, ``world/loops``:
  accepted loop-closure edges between keyframe positions, as they are accepted
* ``tracking/status``: per frame the tracking path and reason (a warning when lost);
  ``tracking/overlap``, ``tracking/icp_fitness``, ``tracking/ms``: scalars over time
* at the end (one frame after the last): ``world/mesh`` (the run's mesh),
  ``world/trajectory`` (the final, corrected trajectory), ``world/loops`` and
  ``world/keyframes`` on the corrected poses

Timelines: ``frame`` (the frame's index in the sequence) and ``time`` (seconds since the first
frame). The file is written to ``PATH.tmp`` and renamed when complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slam.errors import SlamError
from slam.records import TrackingStatus
from slam.run_folder import CONFIG_FILE, RECORDING_FILE, TRACKING_FILE, RunFolder
from slam.run_folder.provenance import checkout_root
from slam.run_folder.tracking_csv import read_tracking_csv as read_tracking_statuses
from slam.trajectory import Trajectory

if TYPE_CHECKING:
    import open3d as o3d

    from slam.data.base import Frame
    from slam.results import RunResult
    from slam.system import FrameResult

log = logging.getLogger(__name__)

__all__ = [
    "RECORDING_FILE",
    "RerunRecorder",
    "check_recording_path",
    "open_in_viewer",
    "read_tracking_statuses",
    "record_run_folder",
]

TRAJECTORY_BLOCK = 100  # poses per world/odometry/NNN entity (each frame re-logs one block)

_ODOMETRY_RGB = (66, 133, 244)
_FINAL_RGB = (255, 140, 0)
_KEYFRAME_RGB = (52, 168, 83)
_LOOP_RGB = (220, 40, 40, 110)


def viz_install_hint() -> str:
    """How to install the ``viz`` extra (rerun-sdk) into the environment running this: the
    package is not on PyPI, so from its checkout (``pip install -e '.[viz]'`` there)."""
    root = checkout_root()
    if root is None:
        return "pip install 'rerun-sdk>=0.41' (the one package of the extra rgbd-slam[viz])"
    return (
        f"pip install -e '{root}[viz]' (the extra rgbd-slam[viz] from this checkout; it is not "
        "on PyPI), or pip install 'rerun-sdk>=0.41'"
    )


def _rerun() -> Any:
    try:
        import rerun as rr
    except ImportError as exc:
        raise SlamError(
            f"the 3D recording needs rerun-sdk, which is not installed: {viz_install_hint()}"
        ) from exc
    return rr


def check_recording_path(path: str | Path) -> Path:
    """Check before any work that a recording can be written to ``path`` (rerun-sdk installed,
    not a folder); returns it."""
    _rerun()
    path = Path(path)
    if path.is_dir():
        raise SlamError(f"--rerun {path} is a folder: give a file name, e.g. {path / 'run.rrd'}")
    return path


class RerunRecorder:
    """Writes a rerun recording (``.rrd``) of a run, frame by frame (see the module docstring).

    ``image_scale``: colour and depth are logged at 1/``image_scale`` of their resolution (0: no
    images); ``name``: the recording's name in the viewer.
    """

    def __init__(self, path: str | Path, image_scale: int = 4, name: str | None = None) -> None:
        rr = self.rr = _rerun()
        if image_scale < 0:
            raise SlamError(f"image_scale must be >= 0 (0: no images), got {image_scale}")
        self.path = check_recording_path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self.image_scale = image_scale
        self.rec = rr.RecordingStream("rgbd-slam")
        self.rec.save(str(self._tmp), default_blueprint=_blueprint(rr))
        if name:
            self.rec.send_recording_name(name)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)
        self._t0: float | None = None
        self._last: tuple[int, float] | None = None
        self._dt = 1.0 / 30
        self._K: np.ndarray | None = None
        self._blocks: list[list[list[np.ndarray]]] = [[]]  # blocks of strips of positions
        self._in_block = 0
        self._broken = True  # the next pose starts a new strip
        self._kf_pos: dict[int, np.ndarray] = {}  # keyframe frame index -> odometry position
        self._kf_stamps: set[float] = set()
        self._loops: list[tuple[np.ndarray, np.ndarray]] = []
        self.frames = 0
        self.closed = False

    # --- per frame
    def on_frame(self, frame: Frame, result: FrameResult) -> None:
        """The ``on_frame`` hook of :func:`slam.run`: log one frame and what SLAM made of it."""
        self.log_frame(
            frame.index,
            frame.timestamp,
            result.T_world_cam,
            result.status,
            frame.color,
            frame.depth_m,
            frame.K,
            [r.as_json() for r in result.loops],
        )

    def log_frame(
        self,
        index: int,
        timestamp: float,
        T_world_cam: np.ndarray | None,
        status: TrackingStatus | None,
        color: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
        K: np.ndarray | None = None,
        loops: list[dict[str, Any]] | None = None,
    ) -> None:
        """Log one frame: its pose (``None`` when lost), tracking state, images and the loops
        its keyframe closed (loop records as in ``loops.json``; accepted ones are drawn)."""
        rr, rec = self.rr, self.rec
        if self._t0 is None:
            self._t0 = timestamp
        if self._last is not None and timestamp > self._last[1]:
            self._dt = timestamp - self._last[1]
        self._last = (index, timestamp)
        self.frames += 1
        rec.set_time("frame", sequence=index)
        rec.set_time("time", duration=timestamp - self._t0)
        if status is not None:
            ok = status.ok and T_world_cam is not None
            text = f"frame {index}: {status.path}" + (
                f" ({status.reason})" if status.reason else ""
            )
            level = rr.TextLogLevel.INFO if ok else rr.TextLogLevel.WARN
            rec.log("tracking/status", rr.TextLog(text, level=level))
            if ok:
                rec.log("tracking/overlap", rr.Scalars(float(status.overlap)))
                rec.log("tracking/icp_fitness", rr.Scalars(float(status.icp_fitness)))
            rec.log("tracking/ms", rr.Scalars(float(status.ms)))
        if T_world_cam is None:
            self._broken = True
        else:
            T = np.asarray(T_world_cam, float)
            rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self._add_pose(T[:3, 3].copy())
            if status is not None and status.keyframe:
                self._kf_pos[index] = T[:3, 3].copy()
                self._kf_stamps.add(round(float(timestamp), 6))
                self._log_keyframes(list(self._kf_pos.values()))
        if self.image_scale and depth_m is not None and K is not None:
            self._log_images(color, depth_m, K)
        accepted = [c for c in loops or [] if c.get("accepted")]
        for c in accepted:
            a = self._kf_pos.get(int(c.get("query_frame", -1)))
            b = self._kf_pos.get(int(c.get("match_frame", -1)))
            if a is not None and b is not None:
                self._loops.append((a, b))
        if accepted:
            self._log_loops(self._loops)

    def _add_pose(self, p: np.ndarray) -> None:
        block = self._blocks[-1]
        if self._in_block >= TRAJECTORY_BLOCK:
            last = None if self._broken or not block else block[-1][-1]
            block = [[last]] if last is not None else []
            self._blocks.append(block)
            self._in_block = 0
        if self._broken or not block:
            block.append([])
            self._broken = False
        block[-1].append(p)
        self._in_block += 1
        strips = [np.array(s) for s in block]
        self.rec.log(
            f"world/odometry/{len(self._blocks) - 1:03d}",
            self.rr.LineStrips3D(strips, colors=[_ODOMETRY_RGB], radii=[0.003]),
        )

    def _log_keyframes(self, positions: list[np.ndarray], rgb=_KEYFRAME_RGB) -> None:
        self.rec.log(
            "world/keyframes",
            self.rr.Points3D(np.array(positions).reshape(-1, 3), colors=[rgb], radii=[0.008]),
        )

    def _log_loops(self, edges: list[tuple[np.ndarray, np.ndarray]]) -> None:
        strips = [np.array([a, b]) for a, b in edges]
        self.rec.log(
            "world/loops", self.rr.LineStrips3D(strips, colors=[_LOOP_RGB], radii=[0.0015])
        )

    def _log_images(self, color: np.ndarray | None, depth_m: np.ndarray, K: np.ndarray) -> None:
        import cv2

        rr, s = self.rr, self.image_scale
        h, w = depth_m.shape[:2]
        hs, ws = max(h // s, 1), max(w // s, 1)
        if self._K is None or not np.array_equal(K, self._K):
            self._K = np.array(K, float)
            Ks = self._K.copy()
            Ks[:2] *= np.array([[ws / w], [hs / h]])
            self.rec.log(
                "world/camera/image",
                rr.Pinhole(image_from_camera=Ks, resolution=[ws, hs], image_plane_distance=0.1),
            )
        if color is not None:
            small = cv2.resize(color, (ws, hs), interpolation=cv2.INTER_AREA)
            self.rec.log("world/camera/image/rgb", rr.Image(small).compress(jpeg_quality=80))
        d = depth_m[: hs * s : s, : ws * s : s]  # nearest: no mixed depths at edges
        mm = np.clip(np.round(np.nan_to_num(d) * 1000.0), 0, 65535).astype(np.uint16)
        self.rec.log("world/camera/image/depth", rr.DepthImage(mm, meter=1000.0))

    # --- the end
    def log_final(
        self,
        trajectory: Trajectory,
        mesh: o3d.geometry.TriangleMesh | None = None,
        loops: list[dict[str, Any]] | None = None,
        summary: str | None = None,
    ) -> None:
        """Log the run's result one frame after the last: the corrected trajectory, the
        accepted loops and keyframes on it, the mesh and a summary line."""
        from slam.tools.report import loop_edges

        rr, rec = self.rr, self.rec
        index, t = self._last if self._last is not None else (0, 0.0)
        rec.set_time("frame", sequence=index + 1)
        rec.set_time("time", duration=t + self._dt - (self._t0 or 0.0))
        if len(trajectory):
            rec.log(
                "world/trajectory",
                rr.LineStrips3D([trajectory.positions], colors=[_FINAL_RGB], radii=[0.003]),
            )
            accepted = [c for c in loops or [] if c.get("accepted")]
            self._log_loops(loop_edges(trajectory, accepted))
            kf = [
                p
                for tt, p in zip(trajectory.timestamps, trajectory.positions)
                if round(float(tt), 6) in self._kf_stamps
            ]
            if kf:
                self._log_keyframes(kf, _FINAL_RGB)
        if mesh is not None and len(mesh.vertices):
            v = np.asarray(mesh.vertices, np.float32)
            kw: dict[str, Any] = {"triangle_indices": np.asarray(mesh.triangles, np.uint32)}
            if mesh.has_vertex_colors():
                c = np.asarray(mesh.vertex_colors)
                kw["vertex_colors"] = np.clip(np.round(c * 255), 0, 255).astype(np.uint8)
            if mesh.has_vertex_normals():
                kw["vertex_normals"] = np.asarray(mesh.vertex_normals, np.float32)
            rec.log("world/mesh", rr.Mesh3D(vertex_positions=v, **kw))
        if summary:
            rec.log(
                "tracking/status", rr.TextLog(f"finished: {summary}", level=rr.TextLogLevel.INFO)
            )

    def finish(self, result: RunResult) -> Path:
        """Log the result of :func:`slam.run` (:meth:`log_final`) and close the file."""
        from slam.pipeline import summary_line

        loops = result.loop_closer.loops_json()["candidates"] if result.loop_closer else []
        self.log_final(result.trajectory, result.mesh, loops, summary_line(result.metrics))
        return self.close()

    def close(self) -> Path:
        """Flush and close the recording; the file appears under its name only now."""
        if not self.closed:
            self.closed = True
            self.rec.flush()
            self.rec.disconnect()
            os.replace(self._tmp, self.path)
            log.info("wrote the rerun recording %s (%d frames)", self.path, self.frames)
        return self.path

    def abort(self) -> None:
        """Close and delete the unfinished recording (the run failed)."""
        if not self.closed:
            self.closed = True
            self.rec.disconnect()
            self._tmp.unlink(missing_ok=True)


def _blueprint(rr: Any) -> Any:
    """The default layout: the 3D world, the camera images, tracking over time."""
    try:
        rrb = rr.blueprint
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="world", name="3D"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin="world/camera/image/rgb", name="colour"),
                    rrb.Spatial2DView(origin="world/camera/image/depth", name="depth"),
                    rrb.TimeSeriesView(origin="tracking", name="tracking"),
                    rrb.TextLogView(origin="tracking/status", name="status"),
                ),
                column_shares=[3, 1],
            ),
            collapse_panels=False,
        )
    except Exception as exc:  # a blueprint API change must not cost the recording
        log.debug("no default blueprint: %s", exc)
        return None


# ----------------------------------------------------------------------------------------------
# run folders


def _summary(run: RunFolder) -> str | None:
    """The run's summary line from its metrics (``None`` when they are incomplete)."""
    from slam.pipeline import summary_line

    try:
        return summary_line(run.metrics())
    except (KeyError, TypeError, ValueError, SlamError):
        return None


def _mesh(run: RunFolder) -> o3d.geometry.TriangleMesh | None:
    return run.mesh()


def record_run_folder(
    run_dir: str | Path,
    out: str | Path | None = None,
    image_scale: int = 4,
) -> Path:
    """The recording :class:`RerunRecorder` makes during a run, made from a finished run folder:
    poses from ``odometry.txt``, tracking state and keyframes from ``tracking.csv``, loops from
    ``loops.json`` (as finally decided), then ``trajectory.txt`` and ``mesh.ply``. Images are
    read from the sequence named in ``config.yaml`` when it is there (else none are logged).
    ``out``: default ``RUN_DIR/recording.rrd``. Returns the file written."""
    run = RunFolder(run_dir).require_complete()
    out = Path(out) if out is not None else run.file(RECORDING_FILE)
    statuses = run.tracking()
    if statuses is None:
        raise SlamError(
            f"{run.path}: no {TRACKING_FILE} (the run was made with output.save_tracking_log "
            "off); record it again with `slam run --rerun FILE.rrd`"
        )
    odometry = run.odometry()
    trajectory = run.trajectory()
    loops = run.loops() or []
    sequence = _open_run_sequence(run) if image_scale else None
    mesh = _mesh(run)
    by_query: dict[int, list[dict[str, Any]]] = {}
    for c in loops:
        by_query.setdefault(int(c.get("query_frame", -1)), []).append(c)
    poses = odometry if odometry is not None else trajectory
    stamp_row = {round(float(t), 6): k for k, t in enumerate(poses.timestamps)}
    summary = _summary(run)
    rec = RerunRecorder(out, image_scale=image_scale, name=run.path.resolve().name)
    try:
        for st in statuses:
            k = stamp_row.get(round(st.timestamp, 6)) if st.ok else None
            T = None if k is None else poses.poses[k]
            color = depth = K = None
            if sequence is not None and 0 <= st.index < len(sequence):
                try:
                    frame = sequence[st.index]
                    color, depth, K = frame.color, frame.depth_m, frame.K
                except SlamError as exc:
                    log.debug("frame %d not read: %s", st.index, exc)
            rec.log_frame(st.index, st.timestamp, T, st, color, depth, K, by_query.get(st.index))
        rec.log_final(trajectory, mesh, loops, summary)
    except BaseException:
        rec.abort()
        raise
    return rec.close()


def _open_run_sequence(run: RunFolder) -> Any:
    """The run's sequence, to read its images again (``None``, with a warning, when it is not
    here or cannot be opened)."""
    try:
        cfg = run.config()
    except SlamError as exc:
        log.warning("%s: the recording has no images: %s", run.path, exc)
        return None
    path = cfg.dataset.path if cfg is not None else None
    if not path or not Path(path).is_dir():
        log.warning(
            "%s: the run's sequence (%s) is not here; the recording has no images",
            run.path,
            path or f"not recorded in {CONFIG_FILE}",
        )
        return None
    from slam.data.loader import open_sequence

    assert cfg is not None
    try:
        return open_sequence(path, cfg.dataset.layout or "auto", cfg.dataset.calibration or None)
    except SlamError as exc:
        log.warning("%s: cannot open the run's sequence, no images: %s", run.path, exc)
        return None


def no_display_reason(environ: Mapping[str, str] | None = None) -> str | None:
    """Why no viewer window can open here, or ``None``: on Linux and the BSDs (X11, Wayland)
    neither ``$DISPLAY`` nor ``$WAYLAND_DISPLAY`` is set (macOS and Windows always have one)."""
    env = os.environ if environ is None else environ
    if sys.platform in ("darwin", "win32", "cygwin"):
        return None
    if env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"):
        return None
    return "no display ($DISPLAY and $WAYLAND_DISPLAY are not set)"


def open_in_viewer(path: str | Path) -> subprocess.Popen:
    """Start the rerun viewer on a recording; returns the process. A :class:`SlamError` before
    anything starts when there is no display (:func:`no_display_reason`) or no viewer; the
    recording is left in place either way."""
    path = Path(path)
    why = no_display_reason()
    if why is not None:
        raise SlamError(
            f"cannot open the viewer: {why}; the recording is kept in {path}: copy it to a "
            f"machine with a display and open it with `rerun {path.name}` (rerun-sdk of the "
            "version that wrote it), or in the web viewer https://app.rerun.io"
        )
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(exe).is_file() and shutil.which(exe) is None:
        raise SlamError(
            f"the rerun viewer is not installed: {viz_install_hint()}; or open {path} with any "
            "rerun viewer, e.g. https://app.rerun.io"
        )
    return subprocess.Popen([exe, str(path)], start_new_session=True)
