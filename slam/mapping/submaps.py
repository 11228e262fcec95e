"""TSDF submaps: the map is a list of TSDF volumes, each fused in the frame of its anchor keyframe.

Tracking works in the frontend's (odometry) world frame and only ever sees the active submap,
so a loop correction never disturbs it. When poses are corrected, the global model is rebuilt by
re-fusing every submap under its corrected anchor pose.

Re-fusion method: each submap is ray-cast (depth + colour) from a subset of the viewpoints of
the frames fused into it (every ``reintegration_stride``-th, at ``1/reintegration_downsample``
resolution) and those renderings are integrated into a fresh volume at
``T_world_anchor (corrected) @ T_anchor_view``. Chosen over re-integrating the raw frames
because it needs neither the frames in memory nor the input again (a live sensor cannot be
re-read), its cost is set by the number of views rather than frames (measured in
docs/archive/journal.md), and the renderings carry the submap's already-averaged surface.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import weakref
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from slam.camera import scale_intrinsics
from slam.config import MappingConfig
from slam.geometry import inv_T
from slam.mapping.tsdf import Rendering, TSDFVolume

log = logging.getLogger(__name__)


def _write(arrays: dict[str, np.ndarray], path: Path) -> None:
    # TSDFVolume.save's format, written from arrays copied out beforehand: numpy's file writes
    # release the GIL, so this runs beside tracking (Open3D's own VoxelBlockGrid.save holds the
    # GIL for ~0.3 s a submap, stalling the main thread)
    np.savez(path, **arrays)


def _cleanup(writer: ThreadPoolExecutor, folder: Path | None) -> None:
    writer.shutdown(wait=True)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


def _color_u8(r: Rendering) -> np.ndarray | None:
    return None if r.color is None else np.clip(r.color * 255.0 + 0.5, 0, 255).astype(np.uint8)


@dataclass
class Submap:
    """A TSDF volume in the frame of its anchor keyframe, with the viewpoints fused into it.
    A finished submap may wait on disk (``volume`` None, ``path`` set)."""

    id: int
    anchor_kf: int
    T_world_anchor: np.ndarray  # the anchor's odometry pose (frontend world frame)
    volume: TSDFVolume | None
    T_anchor_views: list[np.ndarray] = field(default_factory=list)  # every fused frame
    path: Path | None = None
    saving: Future | None = None  # the background write to ``path``, while it runs
    # its first frames are fused into the previous submap too (False when the new submap
    # starts after a relocalisation or in a new map segment: the two are not a continuous run)
    overlaps_previous: bool = True

    @property
    def n_frames(self) -> int:
        return len(self.T_anchor_views)


class SpillStore:
    """Where finished submaps wait on disk, so memory holds the active submap only: a folder
    (a run folder's submaps folder, kept for resuming; default a temporary folder removed with
    this object) and a background writer thread (numpy's file writes release the GIL, so a
    spill runs beside tracking)."""

    def __init__(self, spill_dir: str | Path | None) -> None:
        if spill_dir is None:
            self.folder = Path(tempfile.mkdtemp(prefix="slam-submaps-"))
            cleanup_dir: Path | None = self.folder
        else:
            self.folder = Path(spill_dir)
            self.folder.mkdir(parents=True, exist_ok=True)
            cleanup_dir = None
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-spill")
        weakref.finalize(self, _cleanup, self._writer, cleanup_dir)

    def spill(self, sm: Submap) -> None:
        """Start writing ``sm``'s volume to disk and drop it from memory."""
        assert sm.volume is not None
        sm.path = self.folder / f"submap_{sm.id:04d}.npz"
        arrays = sm.volume.to_arrays()
        sm.volume = None  # the arrays hold it until the file does
        sm.saving = self._writer.submit(_write, arrays, sm.path)
        log.debug("submap %d spilling to %s", sm.id, sm.path)


class SubmapMap:
    """The frontend's model: ``integrate`` and ``raycast`` take ``T_world_cam`` in the odometry
    frame and act on the active submap. A new submap starts seeded with the previous one's
    surface as seen from its last ``submap_seed_views`` viewpoints (ray-cast, then fused), so
    tracking never faces an empty model; the first ``submap_overlap_frames`` frames of a new
    submap are fused into the previous one too, so neighbouring submaps overlap, and tracking
    ray-casts the previous one meanwhile (:attr:`tracking_submap`)."""

    def __init__(
        self, cfg: MappingConfig, has_color: bool = True, spill_dir: str | Path | None = None
    ) -> None:
        """``spill_dir``: where finished submaps wait (a run folder's ``submaps/``, kept for
        resuming); default a temporary folder removed with this object."""
        self.cfg = cfg
        self.has_color = has_color
        self.submaps: list[Submap] = []
        self._K: np.ndarray | None = None
        self._size: tuple[int, int] | None = None
        self._store = SpillStore(spill_dir) if cfg.spill_submaps else None

    def volume(self, sm: Submap) -> TSDFVolume:
        """The submap's volume, loaded from disk when it was spilled."""
        if sm.saving is not None:
            sm.saving.result()  # the write must be complete before reading it back
            sm.saving = None
        if sm.volume is not None:
            return sm.volume
        assert sm.path is not None
        return TSDFVolume.load(sm.path, self.cfg, self.has_color)

    def flush(self) -> None:
        """Wait until every submap being spilled is on disk."""
        for sm in self.submaps:
            if sm.saving is not None:
                sm.saving.result()
                sm.saving = None

    def _spill(self, sm: Submap) -> None:
        """Move a finished submap to disk (when ``mapping.spill_submaps``)."""
        if self._store is not None and sm.volume is not None:
            self._store.spill(sm)

    # --- submap lifecycle
    @property
    def active(self) -> Submap:
        return self.submaps[-1]

    def start_submap(
        self,
        anchor_kf: int,
        T_world_anchor: np.ndarray,
        seed_from: Submap | None = None,
        seed_views: list[np.ndarray] | None = None,
        continuous: bool = True,
    ) -> Submap:
        """Start a submap anchored at a keyframe. ``continuous`` (tracking went on without a
        break): it is seeded with the previous submap seen from that one's last viewpoints, and
        its first frames are fused into the previous one too. Otherwise (after a
        relocalisation, or in a new map segment) the previous submap is finished at once, and
        the new one is seeded from ``seed_from`` (the submap of the keyframe the frame was
        relocalised against) rendered from ``seed_views`` (odometry-frame poses), if given."""
        capacity = None  # the first submap: mapping.block_count
        if self.submaps:
            # allocating the hash map costs ~7 ms per 1000 blocks and growing it later costs
            # more (a rehash): start with room for 1.5x the previous submap's blocks
            prev_blocks = self.volume(self.submaps[-1]).n_blocks
            capacity = min(self.cfg.block_count, max(2000, int(1.5 * prev_blocks)))
        sm = Submap(
            len(self.submaps),
            anchor_kf,
            np.asarray(T_world_anchor, float).copy(),
            TSDFVolume(self.cfg, self.has_color, capacity),
            overlaps_previous=continuous and bool(self.submaps),
        )
        if self.submaps and continuous:
            prev = self.submaps[-1]
            views = [
                prev.T_world_anchor @ T for T in prev.T_anchor_views[-self.cfg.submap_seed_views :]
            ]
            self._seed(sm, prev, views)
        elif self.submaps:
            self._spill(self.submaps[-1])
            if seed_from is not None and seed_views:
                self._seed(sm, seed_from, seed_views)
        self.submaps.append(sm)
        log.debug("submap %d anchored at keyframe %d", sm.id, anchor_kf)
        return sm

    def _seed(self, new: Submap, source: Submap, T_world_views: list[np.ndarray]) -> None:
        """Fuse ray-casts of ``source`` from the given viewpoints into ``new`` (both anchors are
        odometry-frame poses, so the relative transform is exact)."""
        if self._K is None or self._size is None or new.volume is None:
            return
        f = max(int(self.cfg.reintegration_downsample), 1)
        K = scale_intrinsics(self._K, f)
        w, h = self._size[0] // f, self._size[1] // f
        volume = self.volume(source)
        for T_world_view in T_world_views:
            r = volume.render(K, w, h, inv_T(source.T_world_anchor) @ T_world_view, False)
            if (r.depth_m > 0).any():
                new.volume.integrate(
                    r.depth_m, _color_u8(r), K, inv_T(new.T_world_anchor) @ T_world_view
                )

    def submap_of_keyframe(self, kf_id: int) -> Submap | None:
        """The submap a keyframe's frame was fused into (the last one anchored at or before
        it)."""
        found = None
        for sm in self.submaps:
            if sm.anchor_kf <= kf_id:
                found = sm
        return found

    def on_keyframe(self, kf_id: int, T_world_kf: np.ndarray) -> bool:
        """Start a new submap at this keyframe when the active one has ``submap_keyframes``
        keyframes (0 = a single map) and ``submap_min_frames`` frames (with large motion every
        frame is a keyframe, and a submap of a few frames is too thin a model to track
        against). Returns True when a submap was started."""
        n = self.cfg.submap_keyframes
        if not self.submaps:
            self.start_submap(kf_id, T_world_kf)
            return True
        if (
            n > 0
            and kf_id - self.active.anchor_kf >= n
            and self.active.n_frames >= self.cfg.submap_min_frames
        ):
            self.start_submap(kf_id, T_world_kf)
            return True
        return False

    def _in_overlap(self) -> bool:
        """The active submap is new and its first frames are still fused into the previous one."""
        return (
            self.active.overlaps_previous and self.active.n_frames < self.cfg.submap_overlap_frames
        )

    @property
    def tracking_submap(self) -> Submap:
        """The submap tracking ray-casts: the active one, except during a new submap's overlap
        frames. Then the previous submap holds every frame it had and the new ones too, while
        the new one holds a coarse seed and a few frames: ICP against so thin a model slid
        along a corridor (16 mm in the first frame of a new submap)."""
        return self.submaps[-2] if self._in_overlap() else self.active

    # --- the model interface used by tracking and fusion
    def integrate(
        self, depth_m: np.ndarray, color: np.ndarray | None, K: np.ndarray, T_world_cam: np.ndarray
    ) -> None:
        if not self.submaps:
            self.start_submap(0, T_world_cam)
        if self._K is None:
            self._K, self._size = K.copy(), (depth_m.shape[1], depth_m.shape[0])
        targets = [self.active]
        overlap = self._in_overlap()
        if overlap:
            targets.append(self.submaps[-2])
        for sm in targets:
            T_anchor_cam = inv_T(sm.T_world_anchor) @ T_world_cam
            self.volume(sm).integrate(depth_m, color, K, T_anchor_cam)
            sm.T_anchor_views.append(T_anchor_cam)
        if overlap and self.active.n_frames >= self.cfg.submap_overlap_frames:
            self._spill(self.submaps[-2])  # the previous submap is complete

    @property
    def camera(self) -> tuple[np.ndarray, tuple[int, int]] | None:
        """The intrinsics and image size (width, height) of the frames fused (None before
        the first)."""
        if self._K is None or self._size is None:
            return None
        return self._K.copy(), self._size

    @property
    def depth_max_m(self) -> float:
        """Depth beyond this is never fused (``mapping.depth_max_m``)."""
        return float(self.cfg.depth_max_m)

    def raycast(self, K: np.ndarray, width: int, height: int, T_world_cam: np.ndarray, *args, **kw):
        """Ray-cast the tracking submap from an odometry-frame pose (see TSDFVolume.raycast)."""
        if not self.submaps:
            return Rendering(np.zeros((height, width), np.float32), None, None)
        sm = self.tracking_submap
        return self.volume(sm).raycast(
            K, width, height, inv_T(sm.T_world_anchor) @ T_world_cam, *args, **kw
        )

    @property
    def n_blocks(self) -> int:
        """Blocks of the submaps held in memory."""
        return sum(sm.volume.n_blocks for sm in self.submaps if sm.volume is not None)

    # --- the corrected global model
    def rebuild(
        self,
        T_world_anchors: dict[int, np.ndarray] | None = None,
        include: set[int] | None = None,
        correct_view: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> TSDFVolume:
        """Re-fuse every submap (or those whose ids are in ``include``) into one volume: each
        submap is rendered from its views (every ``reintegration_stride``-th) and each render
        fused where ``correct_view`` moves that view (its odometry pose in, its corrected pose
        out: the surface follows a trajectory that bends inside a submap); without it, the
        submap moves rigidly, under ``T_world_anchors[submap.id]`` (default: the anchors'
        odometry poses)."""
        cfg = self.cfg
        out = TSDFVolume(cfg, self.has_color)
        # a rendered view shows only surfaces that passed the ray-caster's weight threshold in
        # their submap, i.e. were seen by several frames already: one view is enough evidence
        out.mesh_weight_threshold = 1.0
        if self._K is None or self._size is None:
            return out
        f = max(int(cfg.reintegration_downsample), 1)
        K = scale_intrinsics(self._K, f)
        w, h = self._size[0] // f, self._size[1] // f
        stride = max(int(cfg.reintegration_stride), 1)
        for sm in self.submaps:
            if include is not None and sm.id not in include:
                continue
            T_world_anchor = (T_world_anchors or {}).get(sm.id, sm.T_world_anchor)
            views = sm.T_anchor_views[::stride]
            if sm.T_anchor_views and views[-1] is not sm.T_anchor_views[-1]:
                views.append(sm.T_anchor_views[-1])
            volume = self.volume(sm)
            for T_anchor_view in views:
                r = volume.render(K, w, h, T_anchor_view, with_normals=False)
                if not (r.depth_m > 0).any():
                    continue
                if correct_view is not None:
                    T_world_view = correct_view(sm.T_world_anchor @ T_anchor_view)
                else:
                    T_world_view = T_world_anchor @ T_anchor_view
                out.integrate(r.depth_m, _color_u8(r), K, T_world_view)
        log.info(
            "re-fused %d submaps into a global model of %d blocks", len(self.submaps), out.n_blocks
        )
        return out

    def extract_mesh(
        self,
        T_world_anchors: dict[int, np.ndarray] | None = None,
        include: set[int] | None = None,
    ) -> o3d.geometry.TriangleMesh:
        """Marching cubes on the global model under the given anchor poses. A single submap is
        meshed directly (and moved rigidly) instead of being re-fused."""
        chosen = [sm for sm in self.submaps if include is None or sm.id in include]
        if len(chosen) == 1:
            sm = chosen[0]
            mesh = self.volume(sm).extract_mesh()
            T = (T_world_anchors or {}).get(sm.id, sm.T_world_anchor)
            return mesh.transform(T)
        return self.rebuild(T_world_anchors, include).extract_mesh()

    # --- maps built elsewhere
    def adopt(
        self, other: SubmapMap, anchors: dict[int, int], T_world_other: np.ndarray
    ) -> list[int]:
        """Take ``other``'s submaps whose anchor keyframe is in ``anchors`` (its keyframe id ->
        this map's), their anchors moved into this map's world frame by ``T_world_other``
        (a chunk of a parallel run joining the global map); the volumes are shared, not copied.
        Returns the new submaps' ids."""
        if self._K is None:
            self._K, self._size = other._K, other._size
        ids = []
        for sm in other.submaps:
            if sm.anchor_kf not in anchors:
                continue
            if sm.saving is not None:  # a spill must be complete before its file is shared
                sm.saving.result()
                sm.saving = None
            new = Submap(
                len(self.submaps), anchors[sm.anchor_kf], T_world_other @ sm.T_world_anchor,
                sm.volume, list(sm.T_anchor_views), sm.path,
                overlaps_previous=sm.overlaps_previous,
            )  # fmt: skip
            self.submaps.append(new)
            ids.append(new.id)
        return ids

    # --- checkpoints
    def state_dict(self) -> dict:
        """Everything needed to rebuild this object: submap records, and the blocks of the
        submaps held in memory (``volume`` arrays); spilled submaps are referenced by path
        (their files are final once written: :meth:`flush` is called first)."""
        self.flush()
        return {
            "K": self._K,
            "size": self._size,
            "submaps": [
                {
                    "id": sm.id,
                    "anchor_kf": sm.anchor_kf,
                    "T_world_anchor": sm.T_world_anchor,
                    "T_anchor_views": np.array(sm.T_anchor_views).reshape(-1, 4, 4),
                    "path": None if sm.path is None else str(sm.path),
                    "volume": None if sm.volume is None else sm.volume.to_arrays(),
                    "overlaps_previous": sm.overlaps_previous,
                }
                for sm in self.submaps
            ],
        }

    def load_state_dict(self, state: dict) -> None:
        self._K = state["K"]
        self._size = None if state["size"] is None else tuple(state["size"])
        self.submaps = []
        for d in state["submaps"]:
            volume = d["volume"]
            self.submaps.append(
                Submap(
                    d["id"],
                    d["anchor_kf"],
                    np.asarray(d["T_world_anchor"]),
                    None
                    if volume is None
                    else TSDFVolume.from_arrays(volume, self.cfg, self.has_color),
                    list(np.asarray(d["T_anchor_views"])),
                    None if d["path"] is None else Path(d["path"]),
                    overlaps_previous=d["overlaps_previous"],
                )
            )
