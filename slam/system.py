"""The SLAM system as a stepwise object: feed frames one at a time, get each pose as it comes.

::

    system = slam.Slam(slam.SlamConfig(), has_color=True)
    for frame in frames:                 # slam.Frame: depth (m), colour, K, timestamp
        r = system.step(frame)           # FrameResult: r.ok, r.T_world_cam, r.status.path
    result = system.finish()             # RunResult: trajectory, odometry, mesh, metrics

:func:`slam.run` is this loop over a :class:`~slam.data.base.Sequence` (with checkpoints).

A frame's path (:meth:`Slam.step`): prepare it once (tracking depth, intrinsics, features on
demand), track it through the loss state machine (:class:`~slam.loops.recovery.LossRecovery`:
tracking, recovery, relocalisation, new segments), hand a new keyframe to the loop closer and
the bundle adjuster, fuse the frame into the map. The end (:meth:`Slam.finish`): the
keyframes' final poses and every frame bent onto them (:mod:`slam.backend.finalise`), the mesh
and the metrics (:mod:`slam.run_metrics`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.backend.adjuster import BundleAdjuster
from slam.backend.finalise import final_mesh, final_poses, view_correction
from slam.config import SlamConfig
from slam.data.base import Frame, checked_frame
from slam.errors import SlamError
from slam.frontend.tracker import Tracker
from slam.keyframe import Keyframe
from slam.localisation import Localisation
from slam.loops.closer import KeyframeLink, LoopCloser
from slam.loops.recovery import LossRecovery
from slam.loops.relocalisation import Relocaliser
from slam.mapping.submaps import SubmapMap
from slam.records import FrameLog, LoopRecord, TrackingStatus
from slam.results import RunResult
from slam.run_metrics import RunRecord, run_metrics
from slam.saved_map import Map
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)

STATE_VERSION = 3


@dataclass
class FrameResult:
    """What :meth:`Slam.step` says about one frame. ``T_world_cam`` is the frontend's
    (odometry) pose, None when the frame is lost; ``loops``: loop records of the keyframe this
    frame became, if any."""

    index: int
    timestamp: float
    status: TrackingStatus
    T_world_cam: np.ndarray | None
    loops: list[LoopRecord] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.T_world_cam is not None


@dataclass
class TrackedFrame:
    """A frame tracked by another system (a chunk of a parallel run), in this system's world
    frame, for :meth:`Slam.replay`: its status, odometry pose (None: lost), tracking run, and
    when it became a keyframe, the keyframe (ids and segments of this system) and how it joins
    the graph (``link``, as :class:`~slam.loops.closer.KeyframeLink`), and a relocalisation's
    record."""

    status: TrackingStatus
    T_world_cam: np.ndarray | None
    run: int
    keyframe: Keyframe | None = None
    link: KeyframeLink | None = None
    relocalisation: dict[str, Any] | None = None


class FrameClock:
    """Frame intervals: how long since the last frame with a pose, in usual frame intervals,
    and whether a frame follows a gap (a skipped frame, a timestamp jump)."""

    def __init__(self, gap_factor: float) -> None:
        self.gap_factor = gap_factor
        self.skipped = False  # the next frame follows a skipped one
        self.last_t: float | None = None
        self.last_pose_t: float | None = None  # timestamp of the last frame with a pose
        self.dts: deque[float] = deque(maxlen=30)

    def tick(self, t: float) -> tuple[float, bool]:
        """(the time since the last frame with a pose over the usual frame interval, whether
        this frame follows a gap)."""
        ratio, gap = 1.0, self.skipped
        self.skipped = False
        usual = float(np.median(self.dts)) if len(self.dts) >= 3 else 0.0
        if self.last_t is not None:
            dt = t - self.last_t
            jump = usual > 0 and (dt / usual > self.gap_factor or dt <= 0)
            gap = gap or jump
            if dt > 0 and not jump:
                self.dts.append(dt)
        if self.last_pose_t is not None and usual > 0:
            ratio = (t - self.last_pose_t) / usual
        self.last_t = t
        return ratio, gap

    def state_dict(self) -> dict[str, Any]:
        return {"gap": self.skipped, "last_t": self.last_t, "last_pose_t": self.last_pose_t,
                "dts": list(self.dts)}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.skipped = bool(state["gap"])
        self.last_t = state["last_t"]
        self.last_pose_t = state.get("last_pose_t")
        self.dts = deque(state["dts"], maxlen=self.dts.maxlen)


class Slam:
    """Stepwise RGB-D SLAM (see the module docstring). ``has_color``: frames carry colour
    (ORB features, coloured mesh); ``color_registered``: colour pixels are depth's rays;
    ``spill_dir``: where finished submaps wait on disk (a run folder's submaps folder, so a
    checkpoint can refer to them), default a temporary folder. ``map``: a saved map
    (:meth:`slam.saved_map.Map.load`) to localise the frames in instead of mapping them
    (:mod:`slam.localisation`): poses in the map's world frame, nothing fused, no keyframes
    or loops added; frames the map does not explain get no pose."""

    def __init__(
        self,
        config: SlamConfig | None = None,
        has_color: bool = True,
        spill_dir: str | None = None,
        color_registered: bool = True,
        map: Map | None = None,  # noqa: A002 - the public name of the argument
    ) -> None:
        self.cfg = cfg = (config or SlamConfig()).validate()
        self.has_color = has_color
        self.tracker = Tracker(cfg.tracking, has_color, color_registered)
        self.model = SubmapMap(cfg.mapping, has_color, spill_dir)
        self.closer = LoopCloser(
            cfg.loop, cfg.backend, cfg.tracking.depth_max_m, color_registered and has_color
        )
        self.ba = BundleAdjuster(
            cfg.ba, cfg.tracking.downsample, has_color, color_registered,
            cfg.backend.loop_kernel_width,
        )  # fmt: skip
        t = cfg.tracking
        relocaliser = Relocaliser(
            self.closer.verifier, self.closer.database, t.recovery.relocalisation_candidates,
            cfg.loop.exclude_recent_keyframes, t.motion.hypothesis_overlap, t.depth_max_m,
        )  # fmt: skip
        self.recovery = LossRecovery(
            t, self.tracker, self.model, relocaliser, cfg.backend.loop_sigma_m
        )
        self.map = map
        self.localisation = (
            None if map is None else Localisation(cfg, self.tracker, map, self.closer.verifier)
        )
        self.clock = FrameClock(t.motion.gap_factor)
        self.frames = FrameLog()  # the frames with a pose
        self.kf_rows: list[int] = []  # row of each keyframe in ``frames``
        self.statuses: list[TrackingStatus] = []  # every frame stepped
        self.skipped: list[dict[str, Any]] = []
        self.stage_ms = {"load": 0.0, "tracking": 0.0, "integration": 0.0, "loop": 0.0}
        self.elapsed_s = 0.0  # time spent in step() and skip()
        self.finished = False  # finish() was called: no more frames
        self.graph_adjusted = False  # a mid-run BA moved the graph's nodes since it was solved

    # --- frames
    def skip(self, index: int, timestamp: float | None, error: str) -> None:
        """Record a frame that could not be read: it is reported, and the next frame follows a
        gap (its pose must be verified)."""
        log.warning("skipping frame %d: %s", index, error)
        self.skipped.append({"index": index, "error": error})
        self.clock.skipped = True

    def step(self, frame: Frame) -> FrameResult:
        """Track one frame, fuse it, and handle keyframes, loops and relocalisation. A
        malformed frame (bad ``K``, depth not HxW, ...) is a :class:`SlamError` that leaves the
        system as it was; NaN, infinite or negative depth counts as no depth. After
        :meth:`finish` the run is over: a new :class:`Slam` takes new frames."""
        if self.finished:
            raise SlamError(
                f"frame {getattr(frame, 'index', '?')}: step() after finish(): the run is over "
                "(its result was made); start a new slam.Slam for more frames"
            )
        frame = checked_frame(frame)
        t_start = time.perf_counter()
        ratio, gap = self.clock.tick(frame.timestamp)
        prepared = self.tracker.prepare(frame)
        loc = self.localisation
        if loc is not None:
            h, w = frame.depth_m.shape
            loc.saved.check_camera(frame.K, (w, h), f"frame {frame.index}")
            out = loc.track(prepared, ratio, gap)
        else:
            out = self.recovery.track(prepared, ratio, gap)
        T, status = out.T_world_cam, out.status
        t_tracked = time.perf_counter()
        mapping = loc is None
        loops = self._keyframe(out.link) if mapping and T is not None and status.keyframe else []
        t_loop = time.perf_counter()
        if T is not None:
            if mapping:
                self.model.integrate(frame.depth_m, frame.color, frame.K, T)
            run, segment = (
                (loc.run, 0) if loc is not None else (self.recovery.run, self.recovery.segment)
            )
            self.frames.append(frame.index, frame.timestamp, T, run, segment)
            self.clock.last_pose_t = frame.timestamp
        t_end = time.perf_counter()
        self.stage_ms["tracking"] += (t_tracked - t_start) * 1e3
        self.stage_ms["loop"] += (t_loop - t_tracked) * 1e3
        self.stage_ms["integration"] += (t_end - t_loop) * 1e3
        self.elapsed_s += t_end - t_start
        self.statuses.append(status)
        return FrameResult(frame.index, frame.timestamp, status, T, loops)

    def _keyframe(self, link: KeyframeLink | None) -> list[LoopRecord]:
        """A new keyframe: a submap boundary maybe, the pose graph and loop detection, then the
        landmark tracks and (after accepted loops) bundle adjustment."""
        kf = self.tracker.state.keyframes[-1]
        if link is None:
            self.model.on_keyframe(kf.id, kf.T_world_cam)
        return self._add_keyframe(kf, link)

    def _add_keyframe(self, kf: Keyframe, link: KeyframeLink | None) -> list[LoopRecord]:
        """The keyframe's row, the pose graph and loop detection, then bundle adjustment."""
        self.kf_rows.append(len(self.frames))
        loops = self.closer.add_keyframe(kf, link)
        self._bundle_adjust_after(kf, loops, link)
        return loops

    def _bundle_adjust_after(
        self, kf: Keyframe, loops: list[LoopRecord], link: KeyframeLink | None
    ) -> None:
        """Extend the landmark tracks with the new keyframe, merge the tracks of its accepted
        loops (and of the keyframe it was relocalised against), and (``ba.after_loops``, every
        ``ba.loop_interval_keyframes``) adjust globally from the pose graph's solution."""
        closer = self.closer
        poses = closer.keyframe_poses()
        self.ba.add_keyframe(kf, poses, closer.same_map)
        accepted = [r for r in loops if r.accepted]
        for r in accepted:
            self.ba.merge_loop(r.query_kf, r.match_kf, r.T_match_query, poses)
        if link is not None and link.kind == "relocalisation" and link.T_other_kf is not None:
            self.ba.merge_loop(kf.id, link.other, link.T_other_kf, poses)
        if accepted and self.ba.due_after_loop(kf.id):
            res = self.ba.optimise(poses, closer.graph.edges, reason=f"loop at keyframe {kf.id}")
            closer.adopt_poses(res.poses)  # later loop checks and matching start from BA's poses
            self.graph_adjusted = self.graph_adjusted or bool(res.poses)

    def replay(self, f: TrackedFrame) -> list[LoopRecord]:
        """Take a frame tracked elsewhere (:class:`TrackedFrame`): a keyframe takes
        :meth:`step`'s keyframe path (pose graph, loop detection, landmark tracks, bundle
        adjustment); the frame is logged with its pose but neither tracked nor fused (its
        submap comes with :meth:`~slam.mapping.submaps.SubmapMap.adopt`)."""
        t0 = time.perf_counter()
        loops: list[LoopRecord] = []
        s = f.status
        if f.keyframe is not None:
            loops = self._add_keyframe(f.keyframe, f.link)
        if f.T_world_cam is not None:
            self.frames.append(s.index, s.timestamp, f.T_world_cam, f.run, s.segment)
        if f.relocalisation is not None:
            self.recovery.relocalisations.append(f.relocalisation)
        self.statuses.append(s)
        self.stage_ms["loop"] += (time.perf_counter() - t0) * 1e3
        return loops

    # --- results
    def finish(self) -> RunResult:
        """The run's result: the final trajectory (every frame follows its keyframes' optimised
        poses), the odometry, the mesh of the global model and the metrics. A localisation
        run's result is its frames' poses in the map, as tracked (:meth:`_localised`)."""
        if self.localisation is not None:
            return self._localised()
        if not len(self.frames):
            raise SlamError(
                "no frame could be tracked: every frame was unreadable or had no usable depth "
                "(see the log and the skipped/lost frames)"
            )
        self.finished = True
        t0 = time.perf_counter()
        closer, frames = self.closer, self.frames
        roots = np.array([closer.segment_root(s) for s in frames.segment])
        poses = final_poses(
            np.stack(frames.pose), np.array(frames.run), self.kf_rows, closer.keyframes,
            closer.graph, self.ba if self.cfg.ba.at_finish else None, self.graph_adjusted,
            corrected=closer.optimisations > 0 or len(set(roots.tolist())) > 1,
        )  # fmt: skip
        self.graph_adjusted = False
        stage_ms = dict(self.stage_ms)
        if poses.ba_ms is not None:
            self.stage_ms["bundle_adjustment"] = stage_ms["bundle_adjustment"] = poses.ba_ms
        # the trajectory is the map component with the most frames; others are reported
        values, counts = np.unique(roots, return_counts=True)
        main_root = int(values[np.argmax(counts)])
        stamps, keep = np.array(frames.timestamp), roots == main_root
        others = {
            int(r): Trajectory(stamps[roots == r], poses.final[roots == r])
            for r in values
            if r != main_root
        }
        mesh, map_blocks, saved = self._mesh(poses, main_root, stage_ms)
        loop_s = self.elapsed_s + self.stage_ms["load"] / 1e3  # the frame loop's wall time
        record = RunRecord(
            list(self.statuses), frames, self.skipped, self.recovery.relocalisations, stage_ms,
            loop_s, loop_s + time.perf_counter() - t0,
        )  # fmt: skip
        metrics = run_metrics(
            record, closer, len(closer.keyframes), len(self.model.submaps),
            self.ba.summary(), len(frames) - sum(len(t) for t in others.values()), main_root,
            len(mesh.vertices) if mesh is not None else 0, map_blocks,
        )  # fmt: skip
        return RunResult(
            Trajectory(stamps[keep].copy(), poses.final[keep]),
            Trajectory(stamps[keep], poses.odometry[keep]),
            mesh, metrics, list(self.statuses), self.cfg, self.model, closer, others,
            Trajectory(stamps[keep].copy(), poses.pose_graph[keep]), saved,
        )  # fmt: skip

    def _localised(self) -> RunResult:
        """A localisation run's result: the poses as tracked in the map (nothing to optimise:
        the map is fixed), no mesh (the map's is the map run's), and how many frames were
        placed in the map, from when; none placed is a result too, not an error."""
        self.finished = True
        loc, frames = self.localisation, self.frames
        assert loc is not None
        stamps = np.array(frames.timestamp, float)
        poses = np.stack(frames.pose) if len(frames) else np.zeros((0, 4, 4))
        loop_s = self.elapsed_s + self.stage_ms["load"] / 1e3
        record = RunRecord(
            list(self.statuses), frames, self.skipped, loc.registrations, dict(self.stage_ms),
            loop_s, loop_s,
        )  # fmt: skip
        metrics = run_metrics(record, self.closer, 0, 0, {}, len(frames), 0, 0, 0)
        metrics.map = str(loc.saved.source) if loc.saved.source is not None else None
        metrics.frames_localised = len(frames)
        metrics.frames_not_localised = len(self.statuses) - len(frames)
        if loc.first_localised is not None:
            metrics.first_localised_frame = loc.first_localised
        if not len(frames):
            log.warning(
                "no frame was localised in the map (%s): a recording of another place, or of "
                "the same place with too little in common with the map's keyframes",
                loc.saved.source,
            )
        traj = Trajectory(stamps, poses)
        return RunResult(traj, Trajectory(stamps.copy(), poses.copy()), None, metrics,
                         list(self.statuses), self.cfg)  # fmt: skip

    def _mesh(
        self, poses: Any, main_root: int, stage_ms: dict[str, float]
    ) -> tuple[Any, int, Map | None]:
        """The mesh of the main map component's submaps under their final anchors (None when
        ``output.save_mesh`` is off), the map's block count and the map to save
        (``output.save_map``: the main component's keyframes at their final poses and its
        TSDF); records the end's timings."""
        kfs, closer, model = self.closer.keyframes, self.closer, self.model
        main = {
            sm.id
            for sm in model.submaps
            if closer.segment_root(kfs[sm.anchor_kf].segment) == main_root
        }
        out_cfg = self.cfg.output
        if not (out_cfg.save_mesh or out_cfg.save_map):
            stage_ms["meshing"] = 0.0
            return None, model.n_blocks, None
        anchors = (
            {sm.id: poses.T_world_kf[sm.anchor_kf] for sm in model.submaps}
            if poses.corrected
            else None
        )
        # the surface follows the final trajectory view by view (it bends inside a submap)
        correct = view_correction(poses.odometry, poses.final) if poses.corrected else None
        include = None if len(main) == len(model.submaps) else main
        out = final_mesh(model, anchors, include, out_cfg.save_mesh, correct)
        if out.reintegration_ms is not None:
            stage_ms["reintegration"] = out.reintegration_ms
        stage_ms["meshing"] = out.meshing_ms
        saved = None
        if out_cfg.save_map and model.camera is not None:
            keyframes = [
                dataclasses.replace(kf, T_world_cam=poses.T_world_kf[kf.id])
                for kf in kfs
                if closer.segment_root(kf.segment) == main_root
            ]
            K, size = model.camera
            saved = Map(
                keyframes, out.volume, out.T_world_volume, 1.0 if out.rebuilt else None, K,
                size, self.has_color, self.tracker.color_registered,
            )  # fmt: skip
        return out.mesh, out.map_blocks, saved

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything the run has built, as plain data and numpy arrays, each component's from
        its own ``state_dict``: keyframes (saved once, named by id elsewhere), tracker, loss
        state machine, loop closer, bundle adjuster, submaps, the frame log and counters.
        ``load_state_dict`` on a new :class:`Slam` with the same config continues the run.
        The state is a snapshot: stepping on does not change it."""
        return {
            "version": STATE_VERSION,
            "config": self.cfg.to_dict(),
            "keyframes": [kf.to_state() for kf in self.tracker.state.keyframes],
            "tracker": self.tracker.state_dict(),
            "recovery": self.recovery.state_dict(),
            "clock": self.clock.state_dict(),
            "closer": self.closer.state_dict(),
            "ba": self.ba.state_dict(),
            "model": self.model.state_dict(),
            "frames": self.frames.state_dict(),
            "kf_rows": list(self.kf_rows),
            "statuses": [s.as_row() for s in self.statuses],
            "skipped": [dict(s) for s in self.skipped],
            "stage_ms": dict(self.stage_ms),
            "elapsed_s": self.elapsed_s,
            "graph_adjusted": self.graph_adjusted,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("version") != STATE_VERSION:
            raise SlamError(
                f"checkpoint state version {state.get('version')} is not {STATE_VERSION} "
                "(written by another version of this package); start the run again"
            )
        _check_same_config(state.get("config"), self.cfg.to_dict())
        keyframes = [Keyframe.from_state(d) for d in state["keyframes"]]
        by_id = {kf.id: kf for kf in keyframes}
        self.tracker.load_state_dict(state["tracker"], by_id)
        self.recovery.load_state_dict(state["recovery"])
        self.clock.load_state_dict(state["clock"])
        self.closer.load_state_dict(state["closer"], by_id)
        self.ba.load_state_dict(state["ba"], by_id)
        self.model.load_state_dict(state["model"])
        self.frames = FrameLog.from_state_dict(state["frames"])
        self.kf_rows = list(state["kf_rows"])
        self.statuses = [TrackingStatus(**row) for row in state["statuses"]]
        self.skipped = list(state["skipped"])
        self.stage_ms = dict(state["stage_ms"])
        self.elapsed_s = float(state["elapsed_s"])
        self.graph_adjusted = bool(state["graph_adjusted"])


#: the config sections that shape a run's state: a state continues only under the same ones
#: (``dataset`` and ``output`` may differ: where the frames are read from, what is written)
STATE_SECTIONS = ("tracking", "mapping", "loop", "backend", "ba")


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix.rstrip("."): d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}."))
    return out


def _check_same_config(saved: Any, current: dict[str, Any]) -> None:
    """A state saved under another configuration (voxel size, downsampling, ...) would continue
    with frames lost and map segments never joined: refused, naming the differences."""
    if not isinstance(saved, dict):
        raise SlamError("the checkpoint state holds no config; start the run again")
    old = {k: v for s in STATE_SECTIONS for k, v in _flat(saved.get(s, {}), f"{s}.").items()}
    new = {k: v for s in STATE_SECTIONS for k, v in _flat(current.get(s, {}), f"{s}.").items()}
    differ = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if differ:
        shown = "; ".join(f"{k}: {old.get(k)!r} in the checkpoint, {new.get(k)!r} now" for k in
                          differ[:5])  # fmt: skip
        more = f" (and {len(differ) - 5} more)" if len(differ) > 5 else ""
        raise SlamError(
            f"the checkpoint was written under another configuration: {shown}{more}; resume "
            "with the configuration the run was started with, or start the run again"
        )
