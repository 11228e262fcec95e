"""Where a run's worst per-frame steps come from: the frames whose odometry step errs most
against ground truth, and, for chosen frames, every frame-to-model alignment tracking tried.

    python benchmarks/trace_steps.py ~/.cache/rgbd-slam/matrix/wall-x1-s1-240-v1
    python benchmarks/trace_steps.py SEQ --frames 85-90 --tree /path/to/other/tree

The run steps a :class:`slam.Slam` frame by frame (the default config, or ``--config``'s
overrides; ``--tree``: import ``slam`` from another source tree). ``--frames A-B`` prints, for each of those frames, each
model-ICP start and result as the error against ground truth relative to frame ``A - 30``
(accumulated local drift, in mm and degrees), its overlap and ICP fitness, whether colour
joined depth, then the path tracking kept and the frame's constraint ratio. The worst steps
are listed with the same local error before and after the step: a step that shrinks it
corrects earlier drift; one that grows it is a new error. This is a diagnostic that wraps
``slam.frontend.alignment.align_to_model``; it changes nothing the run computes.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np


def _local_error(G: np.ndarray, E: np.ndarray, ref: int, k: int) -> tuple[float, float]:
    """Error of frame ``k`` relative to frame ``ref`` (mm, degrees)."""
    inv = np.linalg.inv
    D = inv(inv(G[ref]) @ G[k]) @ (inv(E[ref]) @ E[k])
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(D[:3, 3]) * 1e3), float(np.degrees(np.arccos(cos)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--frames", default="", help="A-B: trace the alignments of these frames")
    ap.add_argument("--worst", type=int, default=6, help="list this many worst steps")
    ap.add_argument("--tree", type=Path, default=None, help="source tree to import slam from")
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides of the default")
    args = ap.parse_args(argv)
    if args.tree is not None:
        sys.path.insert(0, str(args.tree))
    import slam
    from slam.frontend import alignment, tracker
    from slam.pipeline import new_system
    from slam.tools.eval_metrics import ate
    from slam.trajectory import Trajectory, read_tum

    logging.basicConfig(level=logging.ERROR)
    cfg = slam.load_config(args.config)
    seq = slam.open_sequence(args.sequence, cfg.dataset.layout, cfg.dataset.calibration)
    gt = read_tum(args.sequence / "groundtruth.txt")
    first, last = (int(x) for x in args.frames.split("-")) if args.frames else (-1, -2)
    ref = max(first - 30, 0)
    system = new_system(seq, cfg, None)
    est: dict[int, np.ndarray] = {}
    G_of = {}
    t_of: dict[int, float] = {}
    current = {"index": -1}
    coloured: list[int] = []  # frames whose kept pose colour constrained

    def err(T: np.ndarray) -> str:
        k = current["index"]
        G = np.stack([G_of[ref], G_of[k]])
        E = np.stack([est[ref], T])
        t, r = _local_error(G, E, 0, 1)
        return f"{t:.1f} mm / {r:.2f} deg"

    original = alignment.align_to_model

    def traced(cfg_, att, model, T_guess, trusted=True):
        out = original(cfg_, att, model, T_guess, trusted)
        if first <= current["index"] <= last and ref in est:
            print(f"   model ICP from {err(T_guess)} -> {err(out[0])}: overlap {out[2]:.3f}, "
                  f"fitness {out[1].fitness:.3f}, colour {att.photometric > 0}, correction "
                  f"rejected {att.status.model_rejected}")  # fmt: skip
        return out

    alignment.align_to_model = traced
    tracker.align_to_model = traced
    for i in range(len(seq)):
        frame = seq[i]
        G_of[i] = gt.poses[int(np.argmin(np.abs(gt.timestamps - frame.timestamp)))]
        t_of[i] = frame.timestamp
        current["index"] = i
        if first <= i <= last:
            print(f"frame {i}")
        result = system.step(frame)
        if result.T_world_cam is not None:
            est[i] = result.T_world_cam
        if result.status.photometric:
            coloured.append(i)
        if first <= i <= last and ref in est:
            s = result.status
            where = err(result.T_world_cam) if result.T_world_cam is not None else "lost"
            print(f"  kept: {s.path}, {where}, constraint ratio {s.constraint_ratio}")
    idx = sorted(est)
    E = np.stack([est[i] for i in idx])
    G = np.stack([G_of[i] for i in idx])
    inv = np.linalg.inv
    step = np.linalg.norm((inv(inv(G[:-1]) @ G[1:]) @ (inv(E[:-1]) @ E[1:]))[:, :3, 3], axis=1)
    t = np.array([t_of[i] for i in idx])
    odometry = ate(Trajectory(t, G), Trajectory(t, E))  # evo's -a: tracking's estimates as kept
    print(
        f"{args.sequence.name}: median step error {np.median(step) * 1e3:.2f} mm, odometry "
        f"ATE {odometry.rmse * 1e3:.2f} mm; colour kept at frames {coloured}"
    )
    for j in np.argsort(-step)[: args.worst]:
        k, r = j + 1, max(j + 1 - 30, 0)
        b, a = _local_error(G, E, r, k - 1), _local_error(G, E, r, k)
        print(f"frame {idx[k]}: step error {step[j] * 1e3:.2f} mm; error against frame "
              f"{idx[r]}: {b[0]:.1f} mm {b[1]:.2f} deg before, {a[0]:.1f} mm {a[1]:.2f} deg "
              f"after")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
