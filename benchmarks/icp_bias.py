"""How far tracking's ICP moves a frame that starts at its true pose, per ICP kernel and model.

    python benchmarks/icp_bias.py                        # the default rows, frames 1,3,10,40
    python benchmarks/icp_bias.py ~/.cache/rgbd-slam/matrix/desk-x1-s0-240-v1 --frames 1,20

For each sequence (synthetic rows of ``benchmarks/matrix.py``: exact ground truth) and each
frame ``n`` of ``--frames``, ICP starts from the truth twice:

- **frame to frame**: frame ``n``'s tracking depth aligned to frame ``n - 1``'s from their true
  relative pose (``PreparedFrame.icp_to``, as tracking's frame-to-frame step);
- **frame to model**: aligned to the ray-cast of a TSDF fused from frames ``0 .. n - 1`` at their
  true poses (as tracking's frame-to-model step, the model's own weight threshold).

Whatever ICP moves is its bias: with exact depth, 0 for an unbiased kernel and model. Each
variant is the default config with a few settings changed (``VARIANTS``): Open3D's kernel at the
default Huber delta (5 cm, above the 3 cm correspondence gate: plain least squares), at 5 mm,
the project's noise-weighted kernel (``tracking.icp_noise_weighting``), each with and without the
refined ray-cast (``mapping.raycast_refine``). Ground truth builds the models here, nothing is
tracked. Writes ``results/icp-bias.json`` (mm moved, per variant, row, frame and mode).

One more kernel, a prototype that is not in the library (``noise-scaled``): the noise-weighted
point-to-plane cost through Open3D's one-iteration kernel
(``compute_odometry_result_point_to_plane``), the weights folded into the target normals
(``n / sigma(z)``: residuals and Jacobians in units of the depth noise, gate and Huber delta
too), the normals by central differences cut at depth discontinuities, source pixels without a
normal left out (``noise_scaled_icp``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
MATRIX = Path.home() / ".cache" / "rgbd-slam" / "matrix"
ROWS = [
    "room-x1-s0-240-v1",
    "desk-x1-s0-240-v1",
    "desk-x2-s0-exact-240-v1",
    "wall-x1-s1-240-v1",
    "corridor-x1-s0-240-v1",
    "hall-x1-s0-240-v1",
]
VARIANTS: dict[str, dict] = {
    "default": {},
    "huber-5mm": {"tracking": {"huber_delta_m": 0.005}},
    "weighted": {"tracking": {"icp_noise_weighting": True}},
    "refine": {"mapping": {"raycast_refine": True}},
    "huber-5mm+refine": {"tracking": {"huber_delta_m": 0.005}, "mapping": {"raycast_refine": True}},
    "weighted+refine": {
        "tracking": {"icp_noise_weighting": True},
        "mapping": {"raycast_refine": True},
    },
    "noise-scaled": {},
    "noise-scaled+refine": {"mapping": {"raycast_refine": True}},
}
#: the prototype kernel's gate and Huber delta at the finest level, in depth-noise sigmas
SCALED_GATE_SIGMAS = 15.0
SCALED_HUBER_SIGMAS = 3.0


def noise_scaled_icp(source: list, target: list, K: np.ndarray, T: np.ndarray, iterations: list[int],
                     depth_max_m: float = 4.0, coarse_factor: float = 2.0) -> np.ndarray:  # fmt: skip
    """``T_target_source`` by point-to-plane ICP with residuals in units of the target's depth
    noise, through Open3D's one-iteration kernel; ``source``, ``target``: depth pyramids."""
    import open3d.core as o3c
    import open3d.t.pipelines.odometry as odometry

    from slam.camera import DepthNoise, scale_intrinsics
    from slam.frontend.pointcloud import normal_map
    from slam.frontend.weighted_icp import vertex_map

    noise = DepthNoise()

    def maps(depth: np.ndarray, K_l: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = np.where((depth > 0) & (depth < depth_max_m), depth, 0).astype(np.float32)
        vertex = vertex_map(d, K_l)
        normal = normal_map(vertex, f_px=float(K_l[0, 0]))
        unknown = normal[..., 2] == 0
        vertex[unknown] = np.nan
        return vertex, normal / noise.sigma(np.maximum(d, noise.z0_m))[..., None], unknown

    def tensor(a: np.ndarray) -> o3c.Tensor:
        return o3c.Tensor(np.ascontiguousarray(a, np.float32))

    levels = len(iterations)
    for level in reversed(range(levels)):
        K_l = scale_intrinsics(K, 2**level)
        src_vertex, _, _ = maps(source[level], K_l)
        tgt_vertex, tgt_normal, unknown = maps(target[level], K_l)
        tgt_normal[unknown] = np.nan
        args = (tensor(src_vertex), tensor(tgt_vertex), tensor(tgt_normal), o3c.Tensor(K_l))
        scale = coarse_factor**level
        for _ in range(iterations[levels - 1 - level]):
            step = odometry.compute_odometry_result_point_to_plane(
                *args, o3c.Tensor(T), SCALED_GATE_SIGMAS * scale, SCALED_HUBER_SIGMAS * scale
            )
            T = step.transformation.numpy().astype(float) @ T
    return T


def moved_mm(T: np.ndarray) -> float:
    return round(float(np.linalg.norm(T[:3, 3])) * 1e3, 2)


def bias_of_row(
    path: Path, frames: list[int], overrides: dict, scaled: bool
) -> dict[str, list[float]]:
    """mm ICP moves from the truth, frame to frame and frame to model, at each of ``frames``;
    ``scaled``: the prototype kernel instead of tracking's."""
    import slam
    from slam.config import config_from_dict
    from slam.frontend.frame import PreparedFrame
    from slam.frontend.icp import depth_pyramid
    from slam.mapping.tsdf import TSDFVolume
    from slam.trajectory import read_tum

    cfg = config_from_dict(overrides)
    seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
    gt = read_tum(path / "groundtruth.txt")

    def G(i: int) -> np.ndarray:
        return gt.poses[int(np.argmin(np.abs(gt.timestamps - seq[i].timestamp)))]

    def prepared(i: int) -> PreparedFrame:
        return PreparedFrame.build(seq[i], cfg.tracking, None, False)

    def icp(p: PreparedFrame, target: np.ndarray | list[np.ndarray], T: np.ndarray) -> np.ndarray:
        if not scaled:
            return p.icp_to(target, T, cfg.tracking).T_target_source
        levels = len(cfg.tracking.iterations)
        pyramid = target if isinstance(target, list) else depth_pyramid(target, levels)
        return noise_scaled_icp(p.pyramid, pyramid, p.K_track, T, cfg.tracking.iterations)

    volume = TSDFVolume(cfg.mapping, seq.has_color)
    fused = 0
    out: dict[str, list[float]] = {"frame_to_frame": [], "frame_to_model": []}
    for n in frames:
        p, prev = prepared(n), prepared(n - 1)
        T_true = np.linalg.inv(G(n - 1)) @ G(n)
        T = icp(p, prev.pyramid, T_true)
        out["frame_to_frame"].append(moved_mm(np.linalg.inv(T_true) @ T))
        while fused < n:
            f = seq[fused]
            volume.integrate(f.depth_m, f.color, f.K, G(fused))
            fused += 1
        w, h = p.size
        render = volume.raycast(p.K_track, w, h, G(n), False, False, frustum_depth_m=p.depth_m)
        out["frame_to_model"].append(moved_mm(icp(p, render.depth_m, np.eye(4))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="*", type=Path)
    ap.add_argument("--frames", default="1,3,10,40")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "icp-bias.json")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT.parent))
    import logging

    logging.basicConfig(level=logging.ERROR)
    paths = args.sequences or [MATRIX / r for r in ROWS]
    frames = [int(x) for x in args.frames.split(",")]
    result: dict = {"frames": frames, "variants": VARIANTS, "rows": {}}
    for path in paths:
        if not (path / "groundtruth.txt").exists():
            print(f"skipped {path}: no groundtruth.txt (run benchmarks/matrix.py to make it)")
            continue
        per = result["rows"][path.name] = {}
        for name, overrides in VARIANTS.items():
            per[name] = bias_of_row(path, frames, overrides, name.startswith("noise-scaled"))
            f2f, f2m = per[name]["frame_to_frame"], per[name]["frame_to_model"]
            print(f"{path.name:26s} {name:18s} frame to frame {f2f}  frame to model {f2m}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(args.out)
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
