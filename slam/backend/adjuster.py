"""What a run holds for bundle adjustment: the landmark tracks, when to adjust, and the record of
each adjustment (for ``metrics.json``).

::

    ba = BundleAdjuster(cfg.ba, cfg.tracking.downsample, has_color, color_registered)
    ba.add_keyframe(kf, closer.graph.nodes, same_map)        # every keyframe
    ba.merge_loop(query_kf, match_kf, T_match_query, nodes)  # every accepted loop
    result = ba.optimise(closer.graph.nodes, closer.graph.edges)  # global BA
    # result.poses: T_world_kf of every keyframe (frames then follow by elastic correction)

The sequences BA cannot use (see :mod:`slam.backend.bundle_adjustment`): without colour there
are no features, so :meth:`BundleAdjuster.optimise` returns a result with ``skipped`` set and
no poses; with colour not registered to depth, the depth term is weakened
(``ba.unregistered_depth_sigma_m``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from slam.backend.ba_problem import BAProblem, BAResult
from slam.backend.bundle_adjustment import bundle_adjust
from slam.backend.landmarks import LandmarkMap
from slam.backend.pose_graph import Edge
from slam.config import BAConfig
from slam.keyframe import Keyframe

log = logging.getLogger(__name__)


class BundleAdjuster:
    """Landmark tracks and bundle adjustment for one run.

    ``has_color``: frames carry colour (ORB features); ``color_registered``: colour pixels
    and depth pixels are the same rays (TUM: yes; 7-Scenes: no, two cameras).
    ``loop_kernel_width``: the Cauchy width of the pose graph's loop edges when they join the
    problem (``backend.loop_kernel_width``).
    """

    def __init__(
        self,
        cfg: BAConfig,
        downsample: int = 2,
        has_color: bool = True,
        color_registered: bool = True,
        loop_kernel_width: float = 2.0,
    ) -> None:
        self.cfg = cfg
        self.has_color = has_color
        self.color_registered = color_registered
        self.loop_kernel_width = loop_kernel_width
        self.landmarks = LandmarkMap(cfg, downsample)
        self.runs: list[dict[str, Any]] = []  # summary of each adjustment
        self.tracks_ms = 0.0  # time spent building and merging tracks
        self.last_run_keyframe = -1  # newest keyframe at the last adjustment

    # --- what BA can do here
    @property
    def skip_reason(self) -> str | None:
        """Why this run has no bundle adjustment (None: it has)."""
        if not self.cfg.enabled:
            return "disabled (ba.enabled: false)"
        if not self.has_color:
            return "depth-only sequence: no colour, no ORB landmarks; the pose graph stands"
        return None

    @property
    def effective_config(self) -> BAConfig:
        """The configuration BA runs with: ``ba``, with the depth noise raised to
        ``ba.unregistered_depth_sigma_m`` when colour is not registered to depth (the depth
        read at a colour keypoint belongs to a neighbouring ray)."""
        if self.color_registered:
            return self.cfg
        depth = max(self.cfg.depth_sigma_m, self.cfg.unregistered_depth_sigma_m)
        return replace(self.cfg, depth_sigma_m=depth)

    # --- tracks
    def add_keyframe(
        self,
        kf: Keyframe,
        poses: Mapping[int, np.ndarray] | None = None,
        same_map: Callable[[Keyframe, Keyframe], bool] | None = None,
    ) -> None:
        """Extend the landmark tracks with a new keyframe (see
        :meth:`LandmarkMap.add_keyframe`); a no-op when BA is off for this run."""
        if self.skip_reason:
            return
        t0 = time.perf_counter()
        self.landmarks.add_keyframe(kf, poses, same_map)
        self.tracks_ms += (time.perf_counter() - t0) * 1e3

    def merge_loop(
        self,
        query: int,
        match: int,
        T_match_query: np.ndarray,
        poses: Mapping[int, np.ndarray] | None = None,
    ) -> None:
        """Merge the tracks of an accepted loop's two visits (see
        :meth:`LandmarkMap.merge_loop`)."""
        if self.skip_reason:
            return
        t0 = time.perf_counter()
        self.landmarks.merge_loop(query, match, T_match_query, poses)
        self.tracks_ms += (time.perf_counter() - t0) * 1e3

    def due_after_loop(self, newest_keyframe: int) -> bool:
        """Whether an accepted loop at ``newest_keyframe`` should trigger a global BA:
        ``ba.after_loops`` and at least ``ba.loop_interval_keyframes`` keyframes since the
        last adjustment (a revisit often accepts a loop at every keyframe for a while)."""
        if self.skip_reason or not self.cfg.after_loops:
            return False
        if self.last_run_keyframe < 0:
            return True
        return newest_keyframe - self.last_run_keyframe >= self.cfg.loop_interval_keyframes

    # --- adjustment
    def optimise(
        self,
        poses: Mapping[int, np.ndarray],
        edges: Sequence[Edge] = (),
        kf_ids: Iterable[int] | None = None,
        fixed: Iterable[int] | None = None,
        reason: str = "global",
    ) -> BAResult:
        """Bundle adjustment from ``poses`` (``T_world_kf``, e.g. the pose graph's nodes) over
        the keyframes ``kf_ids`` (default all), ``fixed`` ones held; ``edges`` (the pose
        graph's) join with weight ``ba.pose_graph_weight``. Outlier observations are
        removed from the tracks. ``result.poses`` has every keyframe of ``poses``; when BA
        cannot run (see :attr:`skip_reason`, or no landmark seen twice) ``result.skipped`` says
        why and ``result.poses`` is empty."""
        return self._record(self._run(*self._snapshot(poses, edges, kf_ids), fixed), reason)

    def _snapshot(
        self,
        poses: Mapping[int, np.ndarray],
        edges: Sequence[Edge],
        kf_ids: Iterable[int] | None,
    ) -> tuple[BAProblem | None, dict[int, np.ndarray], list[Edge]]:
        if self.skip_reason:
            return None, {}, []
        problem = BAProblem.from_landmarks(self.landmarks, kf_ids).cap_tracks(
            self.cfg.max_observations_per_landmark
        )
        return problem, {k: np.array(T) for k, T in poses.items()}, list(edges)

    def _run(
        self,
        problem: BAProblem | None,
        poses: dict[int, np.ndarray],
        edges: list[Edge],
        fixed: Iterable[int] | None,
    ) -> BAResult:
        if problem is None:
            return BAResult(skipped=self.skip_reason)
        cfg = self.effective_config
        return bundle_adjust(
            problem,
            poses,
            cfg,
            fixed=fixed,
            edges=edges,
            edge_weight=cfg.pose_graph_weight,
            loop_kernel_width=self.loop_kernel_width,
        )

    def _record(self, result: BAResult, reason: str = "global") -> BAResult:
        """Record a finished adjustment and remove its outlier observations from the
        tracks.
        Its poses are dropped (reported as skipped; the pose graph stands) when it rests on
        fewer than ``ba.min_observations_per_keyframe`` inlier observations per keyframe, or
        did not lower the reprojection error (it should by construction; it would take a
        degenerate problem)."""
        why = None
        per_kf = result.observations / max(result.keyframes, 1)
        if result.skipped is not None:
            pass
        elif per_kf < self.cfg.min_observations_per_keyframe:
            why = (
                f"{per_kf:.1f} landmark observations per keyframe (min "
                f"{self.cfg.min_observations_per_keyframe}): too few to improve on the depth "
                "odometry; the pose graph stands"
            )
        elif not result.reprojection_rmse_px_after < result.reprojection_rmse_px_before:
            why = (
                f"the reprojection error did not decrease ({result.reprojection_rmse_px_before:.2f}"
                f" -> {result.reprojection_rmse_px_after:.2f} px); the pose graph stands"
            )
        if why:
            log.warning("bundle adjustment not used: %s", why)
            result.skipped = why
            result.poses = {}
        if result.outliers:
            self.landmarks.detach(result.outlier_kf, result.outlier_feature)
        if result.skipped is None:
            self.last_run_keyframe = max(result.poses, default=self.last_run_keyframe)
        self.runs.append({"reason": reason, **result.summary()})
        return result

    # --- reporting
    def summary(self) -> dict[str, Any]:
        """The ``metrics.json`` ``ba`` object: the last adjustment's figures
        (``reprojection_rmse_px_before/after``, ``landmarks``, ``observations``,
        ``iterations``, ``ms``), plus the number of adjustments, their total time, the track
        statistics and, when BA did not run, why."""
        last = next((r for r in reversed(self.runs) if "skipped" not in r), None)
        out: dict[str, Any] = dict(last) if last else {}
        out.pop("reason", None)
        out["runs"] = sum("skipped" not in r for r in self.runs)
        out["ms_total"] = round(sum(r["ms"] for r in self.runs) + self.tracks_ms, 1)
        out["tracks_ms"] = round(self.tracks_ms, 1)
        out["tracks"] = self.landmarks.stats()
        if self.skip_reason or last is None:
            out["skipped"] = self.skip_reason or (
                self.runs[-1].get("skipped") if self.runs else "never run"
            )
        return out

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "landmarks": self.landmarks.state_dict(),
            "runs": list(self.runs),
            "tracks_ms": self.tracks_ms,
            "last_run_keyframe": self.last_run_keyframe,
        }

    def load_state_dict(self, state: dict[str, Any], keyframes: Mapping[int, Keyframe]) -> None:
        self.landmarks = LandmarkMap.from_state_dict(self.cfg, state["landmarks"], keyframes)
        self.runs = list(state["runs"])
        self.tracks_ms = float(state["tracks_ms"])
        self.last_run_keyframe = int(state["last_run_keyframe"])
