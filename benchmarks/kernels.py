"""Each compiled per-pixel pass against the numpy it replaced, on the same inputs (issue 57's
kernel table).

    python benchmarks/kernels.py                    # two tum-fr1-rpy-500 frames at 320x240
    python benchmarks/kernels.py --sequence demo

Both versions run alternately in this process, ``--repeats`` times each, after a warm-up (the
compile is numba's cache, not timed); the medians and their ratio go to
``benchmarks/results/kernels.json``. The numpy versions are the references the tests check the
kernels against (``tests/frontend/test_depth_kernels.py``, ``test_joint_kernels.py``). A pass
here is milliseconds, so alternating in one process is fair; whole runs are not compared this
way (``benchmarks/alternate.py``). Time nothing else while it runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
from common import ROOT, machine, sequence_path, write_result

sys.path.insert(0, str(ROOT))


def _frames(name: str):
    """Two frames three apart (depth at tracking resolution, grey) and the intrinsics."""
    import slam
    from slam.frontend.pointcloud import downsample_depth
    from slam.frontend.rgbd_image import grey

    cfg = slam.load_config(None)
    seq = slam.open_sequence(sequence_path(name), cfg.dataset.layout, cfg.dataset.calibration)
    out = []
    for i in (100, 103):
        frame = seq[i]
        depth = downsample_depth(frame.depth_m)
        out.append((depth, grey(frame.color, 2)))
    K = seq.calibration.K.copy()
    K[:2] /= 2.0
    K[:2, 2] -= 0.25  # the pinhole convention of a 2x2-averaged level
    return out, K


def _time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e3


def _cases(frames, K):
    from slam.camera import DepthNoise, scale_intrinsics
    from slam.frontend import photometric
    from slam.frontend.icp import projective_agreement
    from slam.frontend.pointcloud import downsample_depth, geometry_rows
    from slam.frontend.rgbd_image import RgbdImage
    from slam.frontend.weighted_icp import depth_information, vertex_map
    from slam.geometry import exp_se3
    from tests.frontend.reference import geometry_reference, normal_map
    from tests.frontend.test_depth_kernels import (
        _downsample_reference,
        _information_reference,
        _reference,
    )
    from tests.frontend.test_joint_kernels import _warp_reference

    (d0, g0), (d1, g1) = frames
    T = exp_se3(np.array([0.01, -0.005, 0.004, 0.01, 0.005, -0.008]))
    noise = DepthNoise()
    views = [(RgbdImage(d1, g1, K, 1), T), (RgbdImage(d0, g0, K, 1), np.eye(4))]

    def numpy_geometry():
        vertex = vertex_map(d0, K)
        normal = normal_map(vertex, f_px=float(K[0, 0]))
        return geometry_reference(vertex.reshape(-1, 3), normal.reshape(-1, 3))

    def numpy_warp():
        V = vertex_map(d0, K).reshape(-1, 3)
        for image, T_world_src in views:
            _warp_reference(V, K, np.linalg.inv(T_world_src), image.intensity[0], image.depth[0],
                            0.07)  # fmt: skip

    K1 = scale_intrinsics(K, 1)
    return {
        "overlap score (projective_agreement)": (
            lambda: _reference(d0, d1, K1, T, 0.03, 2, noise, 3.0, np.inf),
            lambda: projective_agreement(d0, d1, K1, T, 0.03, 2, noise, 3.0),
        ),
        "depth pyramid level (downsample_depth)": (
            lambda: _downsample_reference(d0),
            lambda: downsample_depth(d0),
        ),
        "target vertices + normals (geometry_rows)": (numpy_geometry, lambda: geometry_rows(d0, K)),
        "frame's own information (depth_information)": (
            lambda: _information_reference(d0, K, 4.0, noise),
            lambda: depth_information(d0, K, 4.0, noise),
        ),
        "two reference views warped (mean_warped_intensity)": (
            numpy_warp,
            lambda: photometric.mean_warped_intensity(d0, K, np.eye(4), views, 0.07),
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="tum-fr1-rpy-500")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    from slam import kernels

    kernels.prepare()
    frames, K = _frames(args.sequence)
    rows = {}
    for name, (old, new) in _cases(frames, K).items():
        old(), new()  # warm-up
        t_old, t_new = [], []
        for _ in range(3):  # alternate the two in blocks
            t_old.append(_time(old, args.repeats))
            t_new.append(_time(new, args.repeats))
        a, b = statistics.median(t_old), statistics.median(t_new)
        rows[name] = {"numpy_ms": round(a, 3), "compiled_ms": round(b, 3), "ratio": round(b / a, 3)}
        print(f"{name}: numpy {a:.3f} ms, compiled {b:.3f} ms ({b / a:.2f}x)")
    h, w = frames[0][0].shape
    write_result(
        "kernels",
        {"sequence": args.sequence, "size": [w, h], "rows": rows, "machine": machine()},
    )


if __name__ == "__main__":
    main()
