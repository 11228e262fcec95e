"""The SLAM system as a stepwise object: feed frames one at a time, get each pose as it comes.

::

    system = slam.Slam(slam.SlamConfig(), has_color=True)
    for frame in frames:                 # slam.Frame: depth (m), colour, K, timestamp
        r = system.step(frame)           # FrameResult: r.ok, r.T_world_cam, r.status.path
    result = system.finish()             # RunResult: trajectory, odometry, mesh, metrics

:func:`slam.run` is this loop over a :class:`~slam.data.base.Sequence` (with checkpoints).

Every frame's tracking is decided on its own: a frame without usable depth, or whose estimate
fails the checks, is *lost* (not fused, no pose written). After a gap (a skipped frame, a
timestamp jump) the motion prediction is not trusted and the pose must be verified. While lost,
each frame is relocalised against all keyframes of the map; if that keeps failing for
``tracking.new_segment_after_lost`` frames, a new map segment starts (a new submap and a new
component of the pose graph), joined to the old map at the first verified revisits.
"""

from __future__ import annotations

import copy
import logging
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.backend.adjuster import BundleAdjuster
from slam.backend.finalise import elastic_correction
from slam.camera import scale_intrinsics
from slam.config import SlamConfig
from slam.data.base import Frame
from slam.frontend.pointcloud import depth_pyramid
from slam.frontend.tracker import Tracker, usable_depth_fraction
from slam.keyframe import FeatureSet, Keyframe, KeyframeView
from slam.loops.closer import KeyframeLink, LoopCloser
from slam.loops.relocalisation import Relocaliser
from slam.mapping.submaps import SubmapMap
from slam.records import TrackingStatus
from slam.results import RunResult
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)

STATE_VERSION = 1


@dataclass
class FrameResult:
    """What :meth:`Slam.step` says about one frame. ``T_world_cam`` is the frontend's
    (odometry) pose, None when the frame is lost; ``loops``: loop records of the keyframe this
    frame became, if any."""

    index: int
    timestamp: float
    status: TrackingStatus
    T_world_cam: np.ndarray | None
    loops: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.T_world_cam is not None


@dataclass
class _Rows:
    """The frames that have a pose, in order: index, timestamp, odometry pose, tracking run
    (a run ends where tracking was lost) and map segment."""

    index: list[int] = field(default_factory=list)
    timestamp: list[float] = field(default_factory=list)
    pose: list[np.ndarray] = field(default_factory=list)
    run: list[int] = field(default_factory=list)
    segment: list[int] = field(default_factory=list)

    def append(self, index: int, t: float, T: np.ndarray, run: int, segment: int) -> None:
        self.index.append(index)
        self.timestamp.append(t)
        self.pose.append(T)
        self.run.append(run)
        self.segment.append(segment)

    def __len__(self) -> int:
        return len(self.index)


class Slam:
    """Stepwise RGB-D SLAM (see the module docstring). ``has_color``: frames carry colour
    (ORB features, coloured mesh); ``work_dir``: where finished submaps wait on disk (a run
    folder's ``submaps/``, so a checkpoint can refer to them), default a temporary folder."""

    def __init__(
        self,
        config: SlamConfig | None = None,
        has_color: bool = True,
        work_dir: str | None = None,
        color_registered: bool = True,
    ) -> None:
        self.cfg = cfg = (config or SlamConfig()).validate()
        self.has_color = has_color
        self.tracker = Tracker(cfg.tracking, has_color=has_color, color_registered=color_registered)
        spill = None if work_dir is None else f"{work_dir}/submaps"
        self.model = SubmapMap(cfg.mapping, with_color=has_color, spill_dir=spill)
        self.closer = LoopCloser(cfg.loop, cfg.backend, cfg.tracking.depth_max_m)
        self.ba = BundleAdjuster(
            cfg.ba,
            cfg.tracking.downsample,
            has_color,
            color_registered,
            cfg.backend.loop_kernel_width,
        )
        self.rows = _Rows()
        self.kf_rows: list[int] = []  # row of each keyframe in ``rows``
        self.statuses: list[TrackingStatus] = []  # every frame stepped
        self.skipped: list[dict[str, Any]] = []
        self.stage_ms = {"load": 0.0, "tracking": 0.0, "integration": 0.0, "loop": 0.0}
        self.elapsed_s = 0.0  # time spent in step() and skip()
        self.relocalisations: list[dict[str, Any]] = []
        self.graph_adjusted = False  # a mid-run BA moved the graph's nodes since it was solved
        self.segment = -1  # the current map segment (-1: not started)
        self.run = -1  # the current tracking run
        self.lost = False
        self.lost_with_depth = 0  # consecutive lost frames that had usable depth
        self._gap = False  # the next frame follows a skipped one
        self._last_t: float | None = None
        self._last_pose_t: float | None = None  # timestamp of the last frame with a pose
        self._dts: deque[float] = deque(maxlen=30)

    @property
    def relocaliser(self) -> Relocaliser:
        t = self.cfg.tracking
        return Relocaliser(
            self.closer.verifier,
            self.closer.database,
            t.relocalisation_candidates,
            self.cfg.loop.exclude_recent_keyframes,
            t.hypothesis_overlap,
            t.depth_max_m,
        )

    # --- frames
    def skip(self, index: int, timestamp: float | None, error: str) -> None:
        """Record a frame that could not be read: it is reported, and the next frame follows a
        gap (its pose must be verified)."""
        log.warning("skipping frame %d: %s", index, error)
        self.skipped.append({"index": index, "error": error})
        self._gap = True

    def _interval(self, t: float) -> tuple[float, bool]:
        """(the time since the last frame with a pose over the usual frame interval, whether
        this frame follows a gap)."""
        ratio, gap = 1.0, False
        usual = float(np.median(self._dts)) if len(self._dts) >= 3 else 0.0
        if self._last_t is not None:
            dt = t - self._last_t
            if usual > 0:
                gap = dt / usual > self.cfg.tracking.gap_factor or dt <= 0
            if dt > 0 and not gap:
                self._dts.append(dt)
        if self._last_pose_t is not None and usual > 0:
            ratio = (t - self._last_pose_t) / usual
        self._last_t = t
        return ratio, gap

    def step(self, frame: Frame) -> FrameResult:
        """Track one frame, fuse it, and handle keyframes, loops and relocalisation."""
        t_start = time.perf_counter()
        tcfg = self.cfg.tracking
        ratio, time_gap = self._interval(frame.timestamp)
        gap = self._gap or time_gap
        self._gap = False
        loops: list[dict[str, Any]] = []
        link: KeyframeLink | None = None
        fraction = usable_depth_fraction(frame.depth_m, tcfg.depth_min_m, tcfg.depth_max_m)
        T: np.ndarray | None = None
        if fraction < tcfg.min_depth_fraction:
            status = TrackingStatus(frame.index, "lost", False, frame.timestamp, gap=gap)
            status.reason = (
                f"no usable depth: {100 * fraction:.1f}% of pixels within "
                f"[{tcfg.depth_min_m}, {tcfg.depth_max_m}] m (min "
                f"{100 * tcfg.min_depth_fraction:.1f}%)"
            )
            self._lose(status)
        elif self.segment < 0:
            T, status, link = self._new_segment(frame, np.eye(4))
        elif self.lost:
            T, status, link = self._recover(frame, ratio)
            if T is None:
                tracked = status
                T, status, link = self._relocalise(frame)
                if T is None:
                    status = tracked
                    status.reason += "; relocalisation: no keyframe verifies"
            if T is None and self.lost_with_depth + 1 >= tcfg.new_segment_after_lost:
                assert self.tracker.state.T_world_prev is not None
                T, status, link = self._new_segment(frame, self.tracker.state.T_world_prev)
            elif T is None:
                self.lost_with_depth += 1
        else:
            T, status = self.tracker.track(
                frame, self.model, verify=gap, dt_ratio=ratio, segment=self.segment
            )
            if T is None:
                self._lose(status)
                self.lost_with_depth = 1
                T2, status2, link = self._relocalise(frame)
                if T2 is not None:
                    T, status = T2, status2
        t_tracked = time.perf_counter()
        if T is not None and status.keyframe:
            kf = self.tracker.state.keyframes[-1]
            self.kf_rows.append(len(self.rows))
            if link is None:
                self.model.on_keyframe(kf.id, kf.T_world_cam)
            loops = self.closer.add_keyframe(kf, link)
            self._bundle_adjust_after(kf, loops, link)
        t_loop = time.perf_counter()
        if T is not None:
            self.model.integrate(frame.depth_m, frame.color, frame.K, T)
            self.rows.append(frame.index, frame.timestamp, T, self.run, self.segment)
            self._last_pose_t = frame.timestamp
        t_end = time.perf_counter()
        self.stage_ms["tracking"] += (t_tracked - t_start) * 1e3
        self.stage_ms["loop"] += (t_loop - t_tracked) * 1e3
        self.stage_ms["integration"] += (t_end - t_loop) * 1e3
        self.elapsed_s += t_end - t_start
        status.timestamp = frame.timestamp
        status.segment = self.segment
        self.statuses.append(status)
        return FrameResult(frame.index, frame.timestamp, status, T, loops)

    def _bundle_adjust_after(
        self, kf: Keyframe, loops: list[dict[str, Any]], link: KeyframeLink | None
    ) -> None:
        """Extend the landmark tracks with the new keyframe, merge the tracks of its accepted
        loops (and of the keyframe it was relocalised against), and (``ba.after_loops``, every
        ``ba.loop_interval_keyframes``) adjust globally from the pose graph's solution."""
        closer = self.closer
        nodes = closer.graph.nodes
        self.ba.add_keyframe(
            kf, nodes, lambda a, b: closer.segment_root(a.segment) == closer.segment_root(b.segment)
        )
        accepted = [r for r in loops if r["accepted"]]
        for r in accepted:
            self.ba.merge_loop(r["query_kf"], r["match_kf"], np.asarray(r["T_match_query"]), nodes)
        if link is not None and link.kind == "relocalisation" and link.T_other_kf is not None:
            self.ba.merge_loop(kf.id, link.other, link.T_other_kf, nodes)
        if accepted and self.ba.due_after_loop(kf.id):
            res = self.ba.optimise(nodes, closer.graph.edges, reason=f"loop at keyframe {kf.id}")
            nodes.update(res.poses)  # later loop checks and matching start from BA's poses
            self.graph_adjusted = self.graph_adjusted or bool(res.poses)

    def _lose(self, status: TrackingStatus) -> None:
        status.path = "lost"
        status.ok = False
        if self.segment >= 0 and not self.lost:
            log.info("frame %d: tracking lost (%s); relocalising", status.index, status.reason)
        if self.segment >= 0:
            self.lost = True
            self.tracker.mark_lost()

    def _new_segment(
        self, frame: Frame, T_world_cam: np.ndarray
    ) -> tuple[np.ndarray, TrackingStatus, KeyframeLink]:
        """Start a map segment at this frame (the first frame, or after a long loss)."""
        self.segment += 1
        self.run += 1
        self.lost = False
        self.lost_with_depth = 0
        status = self.tracker.reset(frame, T_world_cam, "init", self.segment)
        kf = self.tracker.state.keyframes[-1]
        if self.model.submaps:
            log.warning(
                "frame %d: not relocalised after %d lost frames; starting map segment %d",
                frame.index,
                self.cfg.tracking.new_segment_after_lost,
                self.segment,
            )
            self.model.start_submap(kf.id, kf.T_world_cam, continuous=False)
        else:
            self.model.start_submap(kf.id, kf.T_world_cam)
        return kf.T_world_cam.copy(), status, KeyframeLink("segment")

    def _recover(
        self, frame: Frame, ratio: float
    ) -> tuple[np.ndarray | None, TrackingStatus, KeyframeLink | None]:
        """While lost: track the frame against the model as after a gap (prediction extrapolated
        from the last pose over the time since, alternative guesses, verification by ORB
        matches). Tracking goes on in the same run when it verifies."""
        T, status = self.tracker.track(
            frame, self.model, verify=True, dt_ratio=ratio, segment=self.segment
        )
        if T is None:
            return None, status, None
        self.lost = False
        self.lost_with_depth = 0
        status.reason = f"recovered against the model after {ratio:.0f} frame intervals"
        self.relocalisations.append({"frame": frame.index, "method": "model"})
        log.info("frame %d: tracking recovered against the model", frame.index)
        return T, status, None

    def _relocalise(
        self, frame: Frame
    ) -> tuple[np.ndarray | None, TrackingStatus, KeyframeLink | None]:
        """Register the frame against the whole map; on success tracking resumes there."""
        t0 = time.perf_counter()
        keyframes = self.tracker.state.keyframes
        depth = self.tracker.tracking_depth(frame)
        feats = self.tracker.features(frame) or FeatureSet.empty()
        view = KeyframeView(feats, depth, scale_intrinsics(frame.K, self.cfg.tracking.downsample))
        found = self.relocaliser.relocalise(view, keyframes, self.tracker.state.T_world_prev)
        if found is None:
            status = TrackingStatus(frame.index, "lost", False, frame.timestamp)
            status.reason = "lost; relocalisation found no keyframe that verifies"
            status.ms = (time.perf_counter() - t0) * 1e3
            return None, status, None
        match = found.keyframe
        T = found.T_world_cam
        self.run += 1
        self.segment = match.segment
        self.lost = False
        self.lost_with_depth = 0
        status = self.tracker.reset(frame, T, "reloc", self.segment, depth, feats)
        status.overlap = round(found.verification.overlap, 4)
        status.icp_fitness = found.verification.icp_fitness
        status.ransac_inliers = found.verification.inliers
        kf = self.tracker.state.keyframes[-1]
        home = self.model.submap_of_keyframe(match.id)
        if home is not self.model.active:
            self.model.start_submap(
                kf.id, T, seed_from=home, seed_views=[T, match.T_world_cam], continuous=False
            )
        s = self.cfg.backend.loop_sigma_m
        info = found.verification.information / s**2
        self.relocalisations.append(
            {
                "frame": frame.index,
                "method": "keyframe",
                "keyframe": match.id,
                "keyframe_frame": match.index,
            }
        )
        log.info(
            "frame %d: relocalised against keyframe %d (frame %d), %d candidates tried",
            frame.index,
            match.id,
            match.index,
            found.candidates_tried,
        )
        status.ms += (time.perf_counter() - t0) * 1e3
        link = KeyframeLink("relocalisation", match.id, found.verification.T_candidate_query, info)
        return T, status, link

    # --- results
    def components(self) -> dict[int, list[int]]:
        """Map components (joined segments) -> their segment ids."""
        out: dict[int, list[int]] = {}
        for seg in sorted(set(self.rows.segment)):
            out.setdefault(self.closer.segment_root(seg), []).append(seg)
        return out

    def finish(self) -> RunResult:
        """The run's result: the final trajectory (every frame follows its keyframes' optimised
        poses), the odometry, the mesh of the global model and the metrics."""
        if not len(self.rows):
            from slam.errors import SlamError

            raise SlamError(
                "no frame could be tracked: every frame was unreadable or had no usable depth "
                "(see the log and the skipped/lost frames)"
            )
        t0 = time.perf_counter()
        odo_all = np.stack(self.rows.pose)
        runs = np.array(self.rows.run)
        kfs = self.closer.keyframes
        corrected = self.closer.optimisations > 0 or len(self.components()) > 1
        if self.graph_adjusted:
            # the pose graph's own solution (a mid-run BA left its poses in the nodes): the
            # trajectory of the pose graph alone, and where the final BA starts from
            self.closer.graph.optimize()
            self.graph_adjusted = False
        pose_graph_poses = {kf.id: self.closer.T_world_kf(kf.id) for kf in kfs}
        kf_poses = dict(pose_graph_poses)
        if self.cfg.ba.at_finish:
            t_ba = time.perf_counter()
            res = self.ba.optimise(
                self.closer.graph.nodes, self.closer.graph.edges, reason="finish"
            )
            self.stage_ms["bundle_adjustment"] = (time.perf_counter() - t_ba) * 1e3
            kf_poses.update(res.poses)

        def follow(poses: dict[int, np.ndarray]) -> np.ndarray:
            """Every frame follows its keyframes' poses (elastic correction)."""
            return elastic_correction(
                odo_all,
                self.kf_rows,
                [kf.T_world_cam for kf in kfs],
                [poses[kf.id] for kf in kfs],
                runs,
            )

        pose_graph_all = follow(pose_graph_poses) if corrected else odo_all.copy()
        adjusted = any(not np.array_equal(kf_poses[k], pose_graph_poses[k]) for k in kf_poses)
        final_all = follow(kf_poses) if adjusted else pose_graph_all
        corrected = corrected or adjusted
        # the trajectory is the map component with the most frames; others are reported
        seg_root = np.array([self.closer.segment_root(s) for s in self.rows.segment])
        roots, counts = np.unique(seg_root, return_counts=True)
        main_root = int(roots[np.argmax(counts)])
        keep = seg_root == main_root
        stamps = np.array(self.rows.timestamp)
        odometry = Trajectory(stamps[keep], odo_all[keep])
        traj = Trajectory(stamps[keep].copy(), final_all[keep])
        pose_graph = Trajectory(stamps[keep].copy(), pose_graph_all[keep])
        others = {
            int(r): Trajectory(stamps[seg_root == r], final_all[seg_root == r])
            for r in roots
            if r != main_root
        }

        mesh = None
        map_blocks = self.model.n_blocks
        main_submaps = {
            sm.id
            for sm in self.model.submaps
            if self.closer.segment_root(kfs[sm.anchor_kf].segment) == main_root
        }
        include = None if len(main_submaps) == len(self.model.submaps) else main_submaps
        t_mesh = time.perf_counter()
        stage_ms = dict(self.stage_ms)
        if self.cfg.output.save_mesh:
            anchors = (
                {sm.id: kf_poses[sm.anchor_kf] for sm in self.model.submaps} if corrected else None
            )
            if len(main_submaps) > 1:
                volume = self.model.rebuild(anchors, include)
                map_blocks = volume.n_blocks
                stage_ms["reintegration"] = (time.perf_counter() - t_mesh) * 1e3
                t_mesh = time.perf_counter()
                mesh = volume.extract_mesh()
            else:
                mesh = self.model.extract_mesh(anchors, include)
        stage_ms["meshing"] = (time.perf_counter() - t_mesh) * 1e3
        seconds = self.elapsed_s + self.stage_ms["load"] / 1e3 + (time.perf_counter() - t0)
        metrics = self._metrics(stage_ms, seconds, main_root, others, mesh, map_blocks)
        return RunResult(
            traj,
            odometry,
            mesh,
            metrics,
            list(self.statuses),
            self.cfg,
            self.model,
            self.closer,
            others,
            pose_graph,
        )

    def _metrics(
        self,
        stage_ms: dict[str, float],
        seconds: float,
        main_root: int,
        others: dict[int, Trajectory],
        mesh: Any,
        map_blocks: int,
    ) -> dict[str, Any]:
        statuses = self.statuses
        n = len(statuses)
        paths = Counter(s.path for s in statuses)
        lost = [s.index for s in statuses if not s.ok]
        loop_s = self.elapsed_s + self.stage_ms["load"] / 1e3  # the frame loop's wall time
        tracked = [s for s in statuses if s.ok and s.path not in ("init", "reloc")]
        closer = self.closer
        segments = []
        for root, segs in self.components().items():
            rows = [k for k, s in enumerate(self.rows.segment) if closer.segment_root(s) == root]
            segments.append(
                {
                    "id": root,
                    "segments": segs,
                    "frames": len(rows),
                    "first_frame": self.rows.index[rows[0]],
                    "last_frame": self.rows.index[rows[-1]],
                    "in_trajectory": root == main_root,
                }
            )
        return {
            "frames": n,
            "frames_tracked": len(self.rows),
            "frames_in_trajectory": len(self.rows) - sum(len(t) for t in others.values()),
            "frames_skipped": len(self.skipped),
            "skipped": list(self.skipped),
            "lost_frames": lost,
            "relocalisations": len(self.relocalisations),
            "relocalisation_frames": [r["frame"] for r in self.relocalisations],
            "map_segments": segments,
            "segment_joins": list(closer.joins),
            "seconds": round(seconds, 3),
            "fps": round(n / loop_s, 3) if loop_s > 0 else None,
            "fps_tracking_fusion": round(
                n / max((stage_ms["tracking"] + stage_ms["integration"]) / 1e3, 1e-9), 3
            ),
            "stage_ms_per_frame": {
                k: round(v / max(n, 1), 3)
                for k, v in stage_ms.items()
                if k not in ("meshing", "reintegration")
            },
            "stage_ms_total": {
                **{k: round(v, 1) for k, v in stage_ms.items()},
                **{k: round(v, 1) for k, v in closer.ms.items()},
            },
            "tracking_failures": len(lost),
            "tracking_paths": dict(paths),
            "keyframes": len(self.tracker.state.keyframes),
            "submaps": len(self.model.submaps),
            "loops_accepted": closer.loops_accepted,
            "loops_rejected": closer.loops_rejected,
            "loop_detection_ms": round(closer.ms["loop_detection"], 1),
            "optimisation_ms": round(closer.ms["optimisation"], 1),
            "optimisations": closer.optimisations,
            "ba": self.ba.summary(),
            "icp_fitness_mean": round(float(np.mean([s.icp_fitness for s in tracked] or [0])), 4),
            "icp_rmse_mean_m": round(float(np.mean([s.icp_rmse_m for s in tracked] or [0])), 6),
            "mesh_vertices": len(mesh.vertices) if mesh is not None else 0,
            "map_blocks": map_blocks,
        }

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything the run has built, as plain data and numpy arrays: frames and poses so
        far, tracker state, keyframes (ORB features and depth), place-recognition index, pose
        graph and submaps (blocks of those in memory; paths of those spilled to disk).
        ``load_state_dict`` on a new :class:`Slam` with the same config continues the run.
        The state is a snapshot: stepping on does not change it."""
        st = self.tracker.state
        prev = st.prev_features
        return {
            "version": STATE_VERSION,
            "config": self.cfg.to_dict(),
            "keyframes": [_keyframe_state(kf) for kf in st.keyframes],
            "tracker": {
                "T_world_prev": st.T_world_prev,
                "velocity": st.velocity,
                "prev_depth": st.prev_depth,
                "prev_features": None if prev is None else _keyframe_state(prev),
                "rng": self.tracker._rng.bit_generator.state,
                "recent_overlaps": list(st.recent_overlaps),
            },
            "closer": self.closer.state_dict(),
            "ba": copy.deepcopy(self.ba.state_dict()),
            "model": self.model.state_dict(),
            "rows": {k: list(v) for k, v in self.rows.__dict__.items()},
            "kf_rows": list(self.kf_rows),
            "statuses": [s.as_row() for s in self.statuses],
            "skipped": list(self.skipped),
            "stage_ms": dict(self.stage_ms),
            "elapsed_s": self.elapsed_s,
            "relocalisations": list(self.relocalisations),
            "graph_adjusted": self.graph_adjusted,
            "segment": self.segment,
            "run": self.run,
            "lost": self.lost,
            "lost_with_depth": self.lost_with_depth,
            "gap": self._gap,
            "last_t": self._last_t,
            "dts": list(self._dts),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        from slam.errors import SlamError

        if state.get("version") != STATE_VERSION:
            raise SlamError(
                f"checkpoint state version {state.get('version')} is not {STATE_VERSION} "
                "(written by another version of this package); start the run again"
            )
        keyframes = [_keyframe_from_state(d) for d in state["keyframes"]]
        by_id = {kf.id: kf for kf in keyframes}
        st = self.tracker.state
        t = state["tracker"]
        st.keyframes = keyframes
        st.T_world_prev = t["T_world_prev"]
        st.velocity = t["velocity"]
        st.prev_depth = t["prev_depth"]
        st.prev_pyramid = (
            None
            if st.prev_depth is None
            else depth_pyramid(st.prev_depth, len(self.cfg.tracking.iterations))
        )
        st.prev_features = (
            None if t["prev_features"] is None else _keyframe_from_state(t["prev_features"])
        )
        self.tracker._rng.bit_generator.state = t["rng"]
        st.recent_overlaps = list(t["recent_overlaps"])
        self.closer.load_state_dict(state["closer"], by_id)
        self.ba.load_state_dict(state["ba"], by_id)
        self.model.load_state_dict(state["model"])
        self.rows = _Rows(**{k: list(v) for k, v in state["rows"].items()})
        self.kf_rows = list(state["kf_rows"])
        self.statuses = [TrackingStatus(**row) for row in state["statuses"]]
        self.skipped = list(state["skipped"])
        self.stage_ms = dict(state["stage_ms"])
        self.elapsed_s = float(state["elapsed_s"])
        self.relocalisations = list(state["relocalisations"])
        self.graph_adjusted = bool(state["graph_adjusted"])
        self.segment = int(state["segment"])
        self.run = int(state["run"])
        self.lost = bool(state["lost"])
        self.lost_with_depth = int(state["lost_with_depth"])
        self._gap = bool(state["gap"])
        self._last_t = state["last_t"]
        self._dts = deque(state["dts"], maxlen=self._dts.maxlen)


def _keyframe_state(kf: Keyframe) -> dict[str, Any]:
    return {
        "index": kf.index,
        "timestamp": kf.timestamp,
        "T_world_cam": kf.T_world_cam,
        "pixels": kf.features.pixels,
        "descriptors": kf.features.descriptors,
        "points_cam": kf.features.points_cam,
        "octave": kf.features.octave,
        "depth_m": kf.depth_m,
        "K": kf.K,
        "id": kf.id,
        "segment": kf.segment,
    }


def _keyframe_from_state(d: dict[str, Any]) -> Keyframe:
    return Keyframe(
        d["index"],
        d["timestamp"],
        np.asarray(d["T_world_cam"]),
        FeatureSet(d["pixels"], d["descriptors"], d["points_cam"], d.get("octave")),
        d["depth_m"],
        d["K"],
        d["id"],
        d["segment"],
    )
