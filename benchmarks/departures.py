"""How far each tracked frame's depth estimate departs from the constant-velocity prediction,
against the recording's own recent departures, and what the frame's step error was.

    python benchmarks/departures.py ~/.cache/rgbd-slam/matrix/wall-x2-s0-c15-240-v2 [...]
    python benchmarks/departures.py SEQ --config benchmarks/depth_disagreement.yaml --json out.json

The run steps a :class:`slam.Slam` frame by frame (the default config, or ``--config``'s
overrides; ``--tree``: import ``slam`` from another source tree). For every frame that reaches
:meth:`slam.frontend.tracker.Tracker.check_motion` it records, before the check acts: the
departure of depth's estimate from the prediction (m), depth's two estimates' disagreement,
the frame's constraint ratio and whether colour already joined depth; after the run, the
frame's odometry step error against ground truth. Per sequence it prints the departures'
median and the ratio of each frame's departure to the median of the previous frames'
(``--window``), and, for the frames with the largest step errors, those figures: does a
departure several times the recording's usual one single out the frames that slid? This is a
diagnostic; it changes nothing the run computes.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np


def _run(seq_dir: Path, config: Path | None) -> dict[str, list[float]]:
    import slam
    from slam.frontend import tracker
    from slam.geometry import inv_T, translation_norm
    from slam.pipeline import new_system
    from slam.trajectory import read_tum

    cfg = slam.load_config(config)
    seq = slam.open_sequence(seq_dir, cfg.dataset.layout, cfg.dataset.calibration)
    gt = read_tum(seq_dir / "groundtruth.txt")
    rec: dict[int, tuple[float, float, float, bool]] = {}
    original = tracker.Tracker.check_motion

    def recorded(self, att, model):  # type: ignore[no-untyped-def]
        if att.ok and att.T_world_cam is not None and self.state.velocity_known:
            predicted = att.T_world_prev @ att.velocity
            departure = translation_norm(inv_T(predicted) @ att.T_world_cam)
            rec[att.frame.index] = (
                departure, att.depth_disagreement(), att.frame.constraint_ratio,
                att.photometric > 0,
            )  # fmt: skip
        return original(self, att, model)

    tracker.Tracker.check_motion = recorded  # type: ignore[method-assign]
    system = new_system(seq, cfg, None)
    est: dict[int, np.ndarray] = {}
    G_of: dict[int, np.ndarray] = {}
    for i in range(len(seq)):
        frame = seq[i]
        G_of[i] = gt.poses[int(np.argmin(np.abs(gt.timestamps - frame.timestamp)))]
        result = system.step(frame)
        if result.T_world_cam is not None:
            est[i] = result.T_world_cam
    tracker.Tracker.check_motion = original  # type: ignore[method-assign]
    inv = np.linalg.inv
    out: dict[str, list[float]] = {k: [] for k in ("frame", "dep", "dis", "ratio", "col", "err")}
    for i in sorted(rec):
        if i in est and i - 1 in est:
            D = inv(inv(G_of[i - 1]) @ G_of[i]) @ (inv(est[i - 1]) @ est[i])
            for k, v in zip(out, (i, *rec[i], float(np.linalg.norm(D[:3, 3])))):
                out[k].append(float(v))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", type=Path, nargs="+")
    ap.add_argument("--tree", type=Path, default=None, help="source tree to import slam from")
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides of the default")
    ap.add_argument("--window", type=int, default=10, help="recent frames the usual is from")
    ap.add_argument("--worst", type=int, default=5, help="list this many worst steps")
    ap.add_argument("--json", type=Path, default=None, help="write every frame's figures here")
    args = ap.parse_args(argv)
    if args.tree is not None:
        sys.path.insert(0, str(args.tree))
    logging.basicConfig(level=logging.ERROR)
    everything = {}
    for seq_dir in args.sequences:
        r = _run(seq_dir, args.config)
        dep, err = np.array(r["dep"]), np.array(r["err"])
        usual = np.array(
            [np.median(dep[max(0, j - args.window) : j]) if j else np.nan for j in range(len(dep))]
        )
        rel = dep / np.maximum(usual, 1e-6)
        r["rel"] = [float(x) for x in rel]
        everything[seq_dir.name] = r
        ok = np.isfinite(rel)
        print(f"{seq_dir.name}: {len(dep)} frames, departure median {1e3 * np.median(dep):.2f} mm, "
              f"p90 {1e3 * np.percentile(dep, 90):.2f}, max {1e3 * dep.max():.2f}; departure over "
              f"the usual: p50 {np.median(rel[ok]):.1f}, p90 {np.percentile(rel[ok], 90):.1f}, "
              f"frames above 3/4/6: {(rel > 3).sum()}/{(rel > 4).sum()}/{(rel > 6).sum()}; "
              f"step error median {1e3 * np.median(err):.2f} mm")  # fmt: skip
        for j in np.argsort(-err)[: args.worst]:
            print(f"   frame {int(r['frame'][j])}: step error {1e3 * err[j]:.2f} mm, departure "
                  f"{1e3 * dep[j]:.2f} mm ({rel[j]:.1f}x the usual {1e3 * usual[j]:.2f}), "
                  f"disagreement {1e3 * r['dis'][j]:.2f} mm, ratio {r['ratio'][j]:.1f}, "
                  f"colour {bool(r['col'][j])}")  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps(everything))
    return 0


if __name__ == "__main__":
    sys.exit(main())
