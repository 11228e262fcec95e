"""When were a recording's images taken? Frame-to-frame steps of depth alone and of colour
against the ground truth read at shifted instants.

    python benchmarks/step_timing.py                          # tum-fr1-xyz, every 8th frame
    python benchmarks/step_timing.py --sequence tum-fr1-xyz --every 4 --shifts=-60,-30,0

Each frame ``i`` is aligned to frame ``i - 1`` from the ground-truth step, by depth alone
(``PreparedFrame.icp_to``, Open3D's ICP) and by colour joining depth at a photometric weight of
10 (``PreparedFrame.joint_to``; colour decides where both measure). The ground truth is then
read at the frame timestamps plus each shift in ``--shifts``, and each step's rotation error
(mrad) and translation error (mm) against it are reported, medians over the frames.

- **Depth's best shift** is where the motion capture's clock and the depth images' capture
  agree. The rotation error is the sharp measure: a hand-held camera's rotation changes
  direction within tens of milliseconds, its translation more slowly.
- **Colour's best shift** is when the colour was taken. The colour alignment measures the
  motion between the two colour images (weight 10: colour decides), and it is compared with the
  ground truth read at the colour images' stamps (``--colour-time stamped``, the default:
  ``timestamp + color_dt_s``) or at the depth's (``depth``), plus the shift.

The errors include the ground truth's own. A second part places both colour cameras where the
ground truth (at depth's best shift) says they were at ``color_dt_s + --colour-add-ms`` and
reports the steps' errors and their cycle errors (``i - 2 -> i - 1 -> i`` against
``i - 2 -> i``; no ground truth in it), for each offset: colour timed right, and still less
consistent than depth, is a weaker measurement for another reason. Writes
``results/step-timing-<sequence>.json``.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import machine, sequence_path, write_result

import slam
from slam.data.tum import interpolate_poses, read_tum
from slam.frontend.tracker import Tracker
from slam.geometry import inv_T, rotation_angle_deg, translation_norm

WEIGHT = 10.0


def _errors(T_found: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation mm, rotation mrad) of ``T_found`` against ``T_true``."""
    e = inv_T(T_true) @ T_found
    return translation_norm(e) * 1e3, float(np.deg2rad(rotation_angle_deg(e))) * 1e3


class Timing:
    """A sequence, its raw ground truth and tracking's frame preparation."""

    def __init__(self, path) -> None:
        self.cfg = slam.load_config(None)
        self.seq = slam.open_sequence(path, self.cfg.dataset.layout, self.cfg.dataset.calibration)
        if not self.seq.color_registered:
            raise SystemExit(f"{path}: colour not registered to depth")
        self.raw = read_tum(path / "groundtruth.txt")
        self.tracker = Tracker(self.cfg.tracking, self.seq.has_color, self.seq.color_registered)
        self.levels = len(self.cfg.tracking.iterations)

    def truth(self, stamps) -> list[np.ndarray] | None:
        """Ground-truth poses at ``stamps`` (interpolated), None where it does not cover one."""
        g = interpolate_poses(self.raw, np.asarray(stamps, float))
        return list(g.poses) if len(g.poses) == len(stamps) else None

    def prepared(self, indices):
        out = [self.tracker.prepare(self.seq[k]) for k in indices]
        for p in out:
            p.photometric_image(self.levels)
        return out

    def depth_step(self, pa, pb, T_init) -> np.ndarray:
        return pb.icp_to(pa.pyramid, T_init, self.cfg.tracking).T_target_source

    def colour_step(self, pa, pb, T_init, colour_a=None, colour_b=None) -> np.ndarray:
        pb.T_depth_colour = colour_b
        return pb.joint_to(pa.rgbd, T_init, self.cfg.tracking, WEIGHT, colour_a).T_target_source


def shift_sweep(t: Timing, frames: list[int], shifts_ms: list[float], colour_time: str) -> dict:
    """Per shift: median (translation mm, rotation mrad) errors of depth's and colour's steps."""
    found = []
    for i in frames:
        fa, fb = t.seq[i - 1], t.seq[i]
        truth = t.truth([fa.timestamp, fb.timestamp])
        if truth is None:
            continue
        step = inv_T(truth[0]) @ truth[1]
        pa, pb = t.prepared((i - 1, i))
        found.append((fa, fb, t.depth_step(pa, pb, step), t.colour_step(pa, pb, step)))
    rows = {}
    for shift in shifts_ms:
        errs: dict[str, list] = {"depth": [], "colour": []}
        for fa, fb, T_depth, T_colour in found:
            d = shift * 1e-3
            depth = t.truth([fa.timestamp + d, fb.timestamp + d])
            if colour_time == "stamped":
                colour = t.truth(
                    [fa.timestamp + fa.color_dt_s + d, fb.timestamp + fb.color_dt_s + d]
                )
            else:
                colour = depth
            if depth is None or colour is None:
                continue
            errs["depth"].append(_errors(T_depth, inv_T(depth[0]) @ depth[1]))
            errs["colour"].append(_errors(T_colour, inv_T(colour[0]) @ colour[1]))
        rows[f"{shift:g}"] = {
            k: {"mm": round(float(np.median(np.array(v)[:, 0])), 3),
                "mrad": round(float(np.median(np.array(v)[:, 1])), 3), "steps": len(v)}
            for k, v in errs.items()
        }  # fmt: skip
    return rows


def placed_colour(t: Timing, frames: list[int], depth_shift_ms: float, adds_ms: list[float]):
    """Colour cameras placed by the ground truth (read at ``depth_shift_ms``) at
    ``color_dt_s + add``: each step's errors against that ground truth and each triplet's cycle
    error, medians, for depth alone and for colour at each ``add``."""
    d = depth_shift_ms * 1e-3
    keys = ["depth"] + [f"colour{a:+g}ms" for a in adds_ms]
    errs: dict[str, list] = {k: [] for k in keys}
    cycles: dict[str, list] = {k: [] for k in keys}
    for i in frames:
        if i < 2:
            continue
        fr = [t.seq[k] for k in (i - 2, i - 1, i)]
        truth = t.truth([f.timestamp + d for f in fr])
        if truth is None:
            continue
        P = t.prepared((i - 2, i - 1, i))
        found: dict[str, dict] = {k: {} for k in keys}
        for a, b in ((0, 1), (1, 2), (0, 2)):
            step = inv_T(truth[a]) @ truth[b]
            found["depth"][(a, b)] = t.depth_step(P[a], P[b], step)
            for add, key in zip(adds_ms, keys[1:]):
                when = [fr[k].timestamp + fr[k].color_dt_s + add * 1e-3 + d for k in (a, b)]
                colour = t.truth(when)
                if colour is None:
                    break
                cam_a, cam_b = inv_T(truth[a]) @ colour[0], inv_T(truth[b]) @ colour[1]
                found[key][(a, b)] = t.colour_step(P[a], P[b], step, cam_a, cam_b)
        if any(len(f) < 3 for f in found.values()):
            continue
        for k, f in found.items():
            errs[k].append(_errors(f[(1, 2)], inv_T(truth[1]) @ truth[2]))
            cycles[k].append(_errors(f[(0, 2)], f[(0, 1)] @ f[(1, 2)]))
    return {
        k: {"step_mm": round(float(np.median(np.array(errs[k])[:, 0])), 3),
            "step_mrad": round(float(np.median(np.array(errs[k])[:, 1])), 3),
            "cycle_mm": round(float(np.median(np.array(cycles[k])[:, 0])), 3),
            "cycle_mrad": round(float(np.median(np.array(cycles[k])[:, 1])), 3),
            "triplets": len(errs[k])}
        for k in keys
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="tum-fr1-xyz", help="a TUM-layout sequence")
    ap.add_argument("--every", type=int, default=8, help="every n-th frame")
    ap.add_argument("--shifts", default="-60,-50,-40,-30,-20,-10,0,10", help="ms, comma-separated")
    ap.add_argument("--colour-time", choices=("stamped", "depth"), default="stamped")
    ap.add_argument("--colour-add-ms", default="0,10,20", help="ms added to color_dt_s")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    t = Timing(sequence_path(args.sequence))
    frames = list(range(max(args.every, 2), len(t.seq), args.every))
    shifts = [float(s) for s in args.shifts.split(",")]
    sweep = shift_sweep(t, frames, shifts, args.colour_time)
    print("| ground truth read at | depth: mm / mrad | colour: mm / mrad |\n|---|---|---|")
    for s, r in sweep.items():
        dep, col = r["depth"], r["colour"]
        print(f"| {float(s):+g} ms | {dep['mm']:.2f} / {dep['mrad']:.2f} "
              f"| {col['mm']:.2f} / {col['mrad']:.2f} |")  # fmt: skip
    best = min(sweep, key=lambda s: sweep[s]["depth"]["mrad"])
    adds = [float(a) for a in args.colour_add_ms.split(",")]
    placed = placed_colour(t, frames, float(best), adds)
    print(f"\ncolour cameras placed by the ground truth read at {float(best):+g} ms:")
    print("| alignment | step mm / mrad | cycle mm / mrad |\n|---|---|---|")
    for k, r in placed.items():
        print(f"| {k} | {r['step_mm']:.2f} / {r['step_mrad']:.2f} "
              f"| {r['cycle_mm']:.2f} / {r['cycle_mrad']:.2f} |")  # fmt: skip
    settings = {"every": args.every, "colour_time": args.colour_time, "weight": WEIGHT}
    name = f"step-timing-{sequence_path(args.sequence).name}"
    out = {"machine": machine(), "settings": settings, "shift_ms": sweep,
           "depth_best_shift_ms": float(best), "placed_colour": placed}  # fmt: skip
    print(f"written: {write_result(name, out)}")


if __name__ == "__main__":
    main()
