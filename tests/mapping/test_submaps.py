"""TSDF submaps: fusion in anchor frames, re-fusion under moved anchors."""

import numpy as np
import open3d as o3d

from slam.config import MappingConfig
from slam.geometry import exp_se3, inv_T
from slam.mapping.submaps import SubmapMap
from tests.conftest import look_at, render_depth

K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])


def _sphere():
    center, radius = np.array([0.0, 0.0, 1.0]), 0.4
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=120).translate(center)
    return mesh, center, radius


def _fuse(cfg: MappingConfig) -> tuple[SubmapMap, list[np.ndarray]]:
    """Three submaps of 8 views each around a sphere; every 4th view is a keyframe."""
    mesh, center, _ = _sphere()
    model = SubmapMap(cfg, has_color=False)
    poses = []
    for k, ang in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False)):
        T = look_at(center + 1.3 * np.array([np.cos(ang), np.sin(ang), 0.3]), center)
        if k % 4 == 0:
            model.on_keyframe(k // 4, T)
        model.integrate(render_depth(mesh, K, 320, 240, T), None, K, T)
        poses.append(T)
    return model, poses


def _distance_to_sphere(mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    _, center, radius = _sphere()
    v = np.asarray(mesh.vertices)
    assert len(v) > 1000
    return np.abs(np.linalg.norm(v - center, axis=1) - radius)


def test_submaps_are_anchored_and_overlap():
    cfg = MappingConfig(
        submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=2, reintegration_downsample=1
    )
    model, _ = _fuse(cfg)
    assert len(model.submaps) == 3
    assert [sm.anchor_kf for sm in model.submaps] == [0, 2, 4]
    # the first frames of a new submap are also fused into the previous one
    assert [sm.n_frames for sm in model.submaps] == [10, 10, 8]
    # each submap stores its views relative to its anchor
    sm = model.submaps[1]
    np.testing.assert_allclose(sm.T_anchor_views[0], np.eye(4), atol=1e-12)
    # finished submaps wait on disk; only the active one is in memory
    model.flush()
    assert [s.volume is None for s in model.submaps] == [True, True, False]
    assert all(s.path.is_file() for s in model.submaps[:2])


def test_refused_global_model_lies_on_the_surface():
    cfg = MappingConfig(
        submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=2, reintegration_stride=2
    )
    model, _ = _fuse(cfg)
    d = _distance_to_sphere(model.extract_mesh())
    assert np.median(d) < 0.5 * cfg.voxel_size_m, np.median(d)
    assert np.percentile(d, 99) < 1.5 * cfg.voxel_size_m


def test_refusion_follows_corrected_anchors():
    """Moving every anchor by the same rigid correction moves the whole mesh with it."""
    cfg = MappingConfig(
        submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=2, reintegration_stride=2
    )
    model, _ = _fuse(cfg)
    C = exp_se3(np.array([0.05, -0.02, 0.1, 0.3, -0.1, 0.2]))
    anchors = {sm.id: C @ sm.T_world_anchor for sm in model.submaps}
    mesh = model.extract_mesh(anchors).transform(inv_T(C))
    d = _distance_to_sphere(mesh)
    assert np.median(d) < 0.5 * cfg.voxel_size_m, np.median(d)


def test_spilled_and_in_memory_submaps_give_the_same_mesh():
    kw = dict(
        submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=2, reintegration_stride=2
    )
    spilled, _ = _fuse(MappingConfig(**kw))
    kept, _ = _fuse(MappingConfig(**kw, spill_submaps=False))
    assert all(s.volume is not None for s in kept.submaps)
    a, b = spilled.extract_mesh(), kept.extract_mesh()
    # Open3D's parallel kernels are not bit-reproducible run to run, so compare the surfaces
    assert abs(len(a.vertices) - len(b.vertices)) <= 0.02 * len(b.vertices)
    assert np.median(_distance_to_sphere(a)) < 0.5 * 0.01
    assert abs(np.mean(_distance_to_sphere(a)) - np.mean(_distance_to_sphere(b))) < 0.001


def test_single_map_when_submaps_are_disabled():
    model, _ = _fuse(MappingConfig(submap_keyframes=0))
    assert len(model.submaps) == 1
    d = _distance_to_sphere(model.extract_mesh())
    assert np.median(d) < 0.2 * 0.01


def test_refusion_from_few_views_keeps_the_whole_surface():
    """Re-fused from every 3rd view (3 of a submap's 8), the global mesh still covers what the
    single map covers: a rendered view shows only surfaces its submap saw often enough, so one
    view is enough to mesh them. With the single-map weight threshold (3 views) a quarter of the
    surface was lost here (0.73 covered), 28% on the demo, and with 2 views a submap nothing."""
    cfg = MappingConfig(
        submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=2, reintegration_stride=3
    )
    model, _ = _fuse(cfg)
    single, _ = _fuse(MappingConfig(submap_keyframes=0))
    refused = model.extract_mesh()
    ref = np.asarray(single.extract_mesh().vertices)
    tree = o3d.geometry.KDTreeFlann(refused)
    near = [tree.search_knn_vector_3d(p, 1)[2][0] < (2 * cfg.voxel_size_m) ** 2 for p in ref[::10]]
    assert np.mean(near) > 0.97, np.mean(near)  # measured 0.996
    assert np.median(_distance_to_sphere(refused)) < 0.5 * cfg.voxel_size_m


def test_tracking_renders_the_previous_submap_while_the_new_one_is_thin():
    """During a new submap's overlap frames (fused into both) tracking ray-casts the previous
    submap, which holds all it saw; then the new one."""
    cfg = MappingConfig(submap_keyframes=2, submap_min_frames=4, submap_overlap_frames=3)
    mesh, center, _ = _sphere()
    model = SubmapMap(cfg, has_color=False)
    seen = []
    for k, ang in enumerate(np.linspace(0, np.pi, 12, endpoint=False)):
        T = look_at(center + 1.3 * np.array([np.cos(ang), np.sin(ang), 0.3]), center)
        if k % 4 == 0:
            model.on_keyframe(k // 4, T)
        seen.append(model.tracking_submap.id if k else 0)
        model.integrate(render_depth(mesh, K, 320, 240, T), None, K, T)
    # a new submap at frame 8 (keyframe 2): frames 9 and 10 track against submap 0
    assert seen[8:] == [0, 0, 0, 1], seen
    r = model.raycast(K, 320, 240, T)
    assert (r.depth_m > 0).mean() > 0.1
