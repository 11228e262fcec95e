import numpy as np
import open3d as o3d

from slam.config import MappingConfig
from slam.mapping.tsdf import TSDFVolume
from tests.conftest import look_at, render_depth


def _fuse_sphere(voxel: float):
    center, radius = np.array([0.0, 0.0, 1.0]), 0.4
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=120).translate(center)
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    vol = TSDFVolume(MappingConfig(voxel_size_m=voxel, depth_max_m=4.0), with_color=False)
    poses = []
    for ang in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        for elev in (-0.4, 0.4):
            eye = center + 1.3 * np.array(
                [np.cos(ang) * np.cos(elev), np.sin(ang) * np.cos(elev), np.sin(elev)]
            )
            T = look_at(eye, center)
            poses.append(T)
            vol.integrate(render_depth(sphere, K, 320, 240, T), None, K, T)
    return vol, center, radius, K, poses


def test_fused_sphere_mesh_within_one_voxel():
    voxel = 0.01
    vol, center, radius, K, _ = _fuse_sphere(voxel)
    mesh = vol.extract_mesh(weight_threshold=1.0)
    v = np.asarray(mesh.vertices)
    assert len(v) > 1000
    dist = np.abs(np.linalg.norm(v - center, axis=1) - radius)
    assert dist.max() < voxel, dist.max()
    assert dist.mean() < 0.2 * voxel, dist.mean()
    # the whole sphere is covered: vertices in every octant
    octants = {tuple(s) for s in np.where(v - center >= 0, 1, -1)}
    assert len(octants) == 8


def test_raycast_renders_the_surface():
    voxel = 0.01
    vol, center, radius, K, poses = _fuse_sphere(voxel)
    T = poses[0]
    r = vol.render(K, 320, 240, T)
    truth = render_depth(
        o3d.geometry.TriangleMesh.create_sphere(radius, 120).translate(center), K, 320, 240, T
    )
    both = (r.depth_m > 0) & (truth > 0)
    assert both.sum() > 0.9 * (truth > 0).sum()
    # Open3D's ray-caster reads the nearest voxel while marching: its depth carries a bias below
    # one voxel (the marching-cubes mesh is tighter, see the test above)
    assert np.median(np.abs(r.depth_m[both] - truth[both])) < voxel
    # normals (camera frame) match the sphere's and face the camera
    v, u = np.nonzero(both)
    z = r.depth_m[both]
    p_cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1)
    c_cam = T[:3, :3].T @ (center - T[:3, 3])
    true_n = (p_cam - c_cam) / np.linalg.norm(p_cam - c_cam, axis=1, keepdims=True)
    n = r.normals_cam[both]
    assert np.median((n * true_n).sum(1)) > 0.99
    assert ((n * p_cam).sum(1) < 0).mean() > 0.95  # silhouette pixels are grazing
