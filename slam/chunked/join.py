"""The join of a parallel run's chunks into one system.

Consecutive chunks tracked the same frames (their overlap): each such frame gives the earlier
chunk's world frame relative to the later one's (``T_prev_cur = P_i Q_i^-1``), and a robust
mean of those (:func:`fit_overlap`) chains the later chunk onto the earlier one; the loop
verifier checks it on the two chunks' keyframes nearest the cut. Each chunk then hands its
frames, in order, to one fresh :class:`~slam.system.Slam` (:meth:`~slam.system.Slam.replay`):
its keyframes go through the same keyframe path as a sequential run's (pose graph, place
recognition over *all* keyframes, verification, landmark tracks, bundle adjustment), so loops
between chunks close like any other; its submaps join the global map under their anchors
(:meth:`~slam.mapping.submaps.SubmapMap.adopt`). ``Slam.finish`` then does the rest: the final
pose graph and bundle adjustment, every frame bent onto its keyframes, every submap re-fused.

Each overlap's frames are reported by the later chunk: the earlier chunk's keyframes and
submaps that start in its last ``overlap`` frames are dropped (the later chunk holds the same
images).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from slam.chunked.plan import Chunk
from slam.config import SlamConfig
from slam.geometry import exp_se3, inv_T, log_se3, rotation_angle_deg, translation_norm
from slam.keyframe import Keyframe
from slam.loops.closer import KeyframeLink, check_consistency
from slam.system import Slam, TrackedFrame

log = logging.getLogger(__name__)

#: fewer paired frames than this cannot chain two chunks
MIN_PAIRS = 3


@dataclass
class OverlapFit:
    """The earlier chunk's world frame relative to the later's, from their common frames."""

    T_prev_cur: np.ndarray
    pairs: int
    median_mm: float  # residual of the paired frames: translation
    max_mm: float
    median_deg: float  # and rotation
    max_deg: float


def fit_overlap(P: list[np.ndarray], Q: list[np.ndarray], iterations: int = 30) -> OverlapFit:
    """Robust mean (iteratively reweighted, an L1 mean in SE(3)'s tangent) of ``P_i Q_i^-1``
    over paired poses of the same frames in two world frames; residuals in mm and degrees."""
    D = [p @ inv_T(q) for p, q in zip(P, Q)]
    T = D[0]
    for _ in range(iterations):
        err = [inv_T(T) @ d for d in D]
        r = np.array([translation_norm(e) + np.radians(rotation_angle_deg(e)) for e in err])
        w = 1.0 / np.maximum(r, 1e-5)  # metres, with rotations as motion at 1 m
        step = sum(wi * log_se3(e) for wi, e in zip(w, err)) / w.sum()
        T = T @ exp_se3(step)
        if np.linalg.norm(step) < 1e-10:
            break
    err = [inv_T(T) @ d for d in D]
    mm = np.array([translation_norm(e) * 1e3 for e in err])
    deg = np.array([rotation_angle_deg(e) for e in err])
    return OverlapFit(
        T, len(D), float(np.median(mm)), float(mm.max()), float(np.median(deg)), float(deg.max())
    )


@dataclass
class JoinReport:
    """How chunk ``number`` joined the one before it (``chunks.json``)."""

    number: int
    joined: bool
    how: str  # "overlap", "verified keyframes", or "new map segment"
    reason: str
    fit: dict[str, Any] = field(default_factory=dict)
    verification: str = ""

    def as_json(self) -> dict[str, Any]:
        return {
            "chunk": self.number, "joined": self.joined, "how": self.how, "reason": self.reason,
            "overlap_fit": self.fit, "verification": self.verification,
        }  # fmt: skip


class Joiner:
    """Builds the joined system chunk by chunk (:meth:`add`, in order), then ``system``'s
    :meth:`~slam.system.Slam.finish` gives the run's result."""

    def __init__(self, cfg: SlamConfig, has_color: bool, color_registered: bool) -> None:
        self.cfg = cfg
        self.system = Slam(cfg, has_color=has_color, color_registered=color_registered)
        self.reports: list[JoinReport] = []
        self._last: Keyframe | None = None  # the joined system's newest keyframe
        self._last_local: Keyframe | None = None  # the same keyframe in its chunk's frame
        self._last_chunk: Slam | None = None
        self._T_world_last_chunk = np.eye(4)
        self._segments = 0
        self._runs = 0

    def add(self, chunk: Chunk, part: Slam, cut_index: float) -> JoinReport | None:
        """Chunk ``part`` (a finished chunk's system), reporting its frames before sequence
        index ``cut_index`` (the next chunk reports the rest)."""
        kfs = [kf for kf in part.closer.keyframes if kf.index < cut_index]
        report, T_world_part, joined = None, np.eye(4), False
        if self._last is not None and kfs and self._last_chunk is not None:
            report, T_world_part, joined = self._join(chunk.number, part, kfs[0])
            self.reports.append(report)
        elif self._last is not None:
            self.reports.append(
                JoinReport(chunk.number, False, "none", "the chunk has no tracked keyframe")
            )
        self._replay(part, kfs, cut_index, T_world_part, joined)
        if kfs:
            self._last_chunk, self._last_local = part, kfs[-1]
            self._T_world_last_chunk = T_world_part
        return report

    # --- chaining
    def _join(
        self, number: int, part: Slam, first: Keyframe
    ) -> tuple[JoinReport, np.ndarray, bool]:
        """The part's world frame in the joined one: from the overlap's paired frames, else
        from verifying its first keyframe against the previous chunk's last; else it starts
        a new map segment (revisits may join it later)."""
        prev, last, last_local = self._last_chunk, self._last, self._last_local
        assert prev is not None and last is not None and last_local is not None
        rows = {
            i: k
            for k, i in enumerate(prev.frames.index)
            if prev.frames.segment[k] == last_local.segment
        }
        P, Q = [], []
        for k, i in enumerate(part.frames.index):
            if i in rows and part.frames.segment[k] == first.segment:
                P.append(prev.frames.pose[rows[i]])
                Q.append(part.frames.pose[k])
        lc = self.cfg.loop
        ver = self.system.closer.verifier.verify(first.view(), last_local.view())
        fit = fit_overlap(P, Q) if len(P) >= MIN_PAIRS else None
        T_world_prev = self._T_world_last_chunk
        if fit is not None:
            T_world_part = T_world_prev @ fit.T_prev_cur
            if ver.accepted:
                T_pred = inv_T(last.T_world_cam) @ T_world_part @ first.T_world_cam
                check_consistency(ver, T_pred, 0.0, lc)
            fit_json = {
                "pairs": fit.pairs, "median_mm": round(fit.median_mm, 3),
                "max_mm": round(fit.max_mm, 3), "median_deg": round(fit.median_deg, 4),
                "max_deg": round(fit.max_deg, 4),
            }  # fmt: skip
            if fit.median_mm <= lc.consistency_m * 1e3 and fit.median_deg <= lc.consistency_deg:
                log.info("chunk %d chained through %d overlapping frames (median residual %.1f "
                         "mm, %.2f deg)", number, fit.pairs, fit.median_mm, fit.median_deg)  # fmt: skip
                return JoinReport(number, True, "overlap", "paired frames agree", fit_json,
                                  ver.reason), T_world_part, True  # fmt: skip
            reason = (
                f"the overlap's {fit.pairs} paired frames disagree: median residual "
                f"{fit.median_mm:.1f} mm / {fit.median_deg:.2f} deg (tolerance "
                f"{lc.consistency_m * 1e3:.0f} mm / {lc.consistency_deg} deg)"
            )
        else:
            fit_json = {"pairs": len(P)}
            reason = f"{len(P)} frames tracked by both chunks (< {MIN_PAIRS})"
        if ver.accepted:  # the two keyframes registered directly
            T_world_part = last.T_world_cam @ ver.T_candidate_query @ inv_T(first.T_world_cam)
            return JoinReport(number, True, "verified keyframes", reason, fit_json,
                              ver.reason), T_world_part, True  # fmt: skip
        log.warning("chunk %d not chained to chunk %d (%s; verification: %s): it starts a new "
                    "map segment", number, number - 1, reason, ver.reason)  # fmt: skip
        return (
            JoinReport(number, False, "new map segment", reason, fit_json, ver.reason),
            (T_world_prev @ (fit.T_prev_cur if fit is not None else np.eye(4))),
            False,
        )

    # --- replay
    def _replay(
        self, part: Slam, kfs: list[Keyframe], cut_index: float, T_world_part: np.ndarray,
        joined: bool,
    ) -> None:  # fmt: skip
        g = self.system
        g.closer.remember(part.closer)  # the chunk's verifications are not made again
        segments: dict[int, int] = {}
        if joined and kfs and self._last is not None:
            segments[kfs[0].segment] = self._last.segment
        runs: dict[int, int] = {}

        def segment(s: int) -> int:
            if s < 0:  # lost before the chunk's first segment
                return s
            if s not in segments:
                segments[s], self._segments = self._segments, self._segments + 1
            return segments[s]

        def run(r: int) -> int:
            if r not in runs:
                runs[r], self._runs = self._runs, self._runs + 1
            return runs[r]

        rows = {i: k for k, i in enumerate(part.frames.index)}
        by_index = {kf.index: kf for kf in kfs}
        reloc_edges = {e.j: e for e in part.closer.graph.edges if e.kind == "relocalisation"}
        relocs = {r["frame"]: r for r in part.recovery.relocalisations}
        ids: dict[int, int] = {}
        prev_local: Keyframe | None = None
        for s in part.statuses:
            if s.index >= cut_index:
                break
            row = rows.get(s.index)
            T = None if row is None else T_world_part @ part.frames.pose[row]
            kf, link = by_index.get(s.index) if T is not None else None, None
            gkf = None
            if kf is not None:
                if kf.id in reloc_edges and reloc_edges[kf.id].i in ids:
                    e = reloc_edges[kf.id]
                    link = KeyframeLink("relocalisation", ids[e.i], e.T_i_j, e.information)
                elif (prev_local is None and not joined) or (
                    prev_local is not None and kf.segment != prev_local.segment
                ):
                    link = KeyframeLink("segment")
                ids[kf.id] = len(g.closer.keyframes)
                gkf = replace(kf, id=ids[kf.id], T_world_cam=T_world_part @ kf.T_world_cam,
                              segment=segment(kf.segment))  # fmt: skip
                prev_local = kf
            status = replace(s, segment=segment(s.segment))
            frame_run = run(part.frames.run[row]) if row is not None else -1
            g.replay(TrackedFrame(status, T, frame_run, gkf, link, relocs.get(s.index)))
            if gkf is not None:
                self._last = gkf
        g.skipped.extend(dict(sk) for sk in part.skipped if sk["index"] < cut_index)
        g.model.adopt(part.model, ids, T_world_part)
        for k, v in part.stage_ms.items():
            if k != "loop":  # the joined system's loop time is its own (replay)
                g.stage_ms[k] = g.stage_ms.get(k, 0.0) + v
