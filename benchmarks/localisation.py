"""A recording split in two: the first part mapped, the second localised in that map, against
one run over all frames and against mapping the second part (issue 58's measures).

    python benchmarks/localisation.py tum-fr1-xyz --split 400
    python benchmarks/localisation.py demo --split 150 --repeats 3

Every run is a fresh ``slam run`` process (default config): the map run (frames before
``--split``), one run over all frames, then ``--repeats`` alternating pairs of mapping the
frames from ``--split`` on and localising them in the map (``--map``, ``--first-frame``).
Writes benchmarks/results/localisation-<sequence>.json: frames localised, the first, the
localisation's ATE in the map's frame and aligned, the full run's error on the same frames
(its own alignment over all frames), and the localisation/mapping time ratio (median of the
pairs). Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import ROOT, machine, sequence_path, write_result

sys.path.insert(0, str(ROOT))

from slam.tools import eval as slam_eval  # noqa: E402
from slam.trajectory import Trajectory, read_tum  # noqa: E402

KEYS = (
    "frames", "frames_localised", "frames_not_localised", "first_localised_frame", "seconds",
    "fps", "ate_rmse_m", "ate_rmse_map_frame_m",
)  # fmt: skip


def slam_run(sequence: Path, out: Path, *args: str) -> dict:
    """One ``slam run`` in a fresh process; its metrics."""
    cmd = [sys.executable, "-m", "slam", "run", str(sequence), "--out", str(out), "-q", *args]
    subprocess.run(cmd, check=True, cwd=ROOT)
    return json.loads((out / "metrics.json").read_text())


def error_on(gt: Trajectory, full: Trajectory, frames: Trajectory) -> float:
    """The full run's ATE RMSE on the frames of ``frames`` (by timestamp), under the full
    run's own alignment over all its frames."""
    moved = slam_eval.transformed(full, slam_eval.alignment(gt, full))
    want = set(np.round(frames.timestamps, 6))
    keep = np.array([round(t, 6) in want for t in moved.timestamps])
    sub = Trajectory(moved.timestamps[keep], moved.poses[keep])
    return slam_eval.ate(gt, sub, align=False).rmse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="demo, or a folder under ../shared/datasets")
    ap.add_argument("--split", type=int, required=True, help="the first frame localised")
    ap.add_argument("--repeats", type=int, default=3, help="pairs of mapping / localising")
    args = ap.parse_args()
    path = sequence_path(args.sequence)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        mapped = slam_run(path, root / "map", "--max-frames", str(args.split))
        full = slam_run(path, root / "full")
        pairs = []
        for i in range(args.repeats):
            rest = ["--first-frame", str(args.split)]
            m = slam_run(path, root / f"mapping{i}", *rest)
            loc = slam_run(path, root / f"loc{i}", *rest, "--map", str(root / "map"))
            pairs.append(
                {
                    "mapping": {k: m.get(k) for k in KEYS},
                    "localisation": {k: loc.get(k) for k in KEYS},
                    "seconds_ratio": loc["seconds"] / m["seconds"],
                }  # fmt: skip
            )
            print(f"pair {i}: localisation {loc['seconds']:.1f} s, mapping {m['seconds']:.1f} s")
        gt, _ = slam_eval.sequence_ground_truth(path)
        loc_traj = read_tum(root / "loc0" / "trajectory.txt")
        full_err = (
            error_on(gt, read_tum(root / "full" / "trajectory.txt"), loc_traj)
            if gt is not None and len(loc_traj)
            else None
        )
    data = {
        "sequence": args.sequence,
        "split": args.split,
        "map_run": {k: mapped.get(k) for k in ("frames", "ate_rmse_m", "seconds")},
        "full_run": {k: full.get(k) for k in ("frames", "ate_rmse_m", "seconds")},
        "full_run_error_on_localised_frames_m": full_err,
        "pairs": pairs,
        "median_seconds_ratio_localisation_over_mapping": statistics.median(
            p["seconds_ratio"] for p in pairs
        ),
        "machine": machine(),
    }
    out = write_result(f"localisation-{Path(args.sequence).name}", data)
    loc = pairs[0]["localisation"]
    print(
        f"{out}: {loc['frames_localised']} of {loc['frames']} localised; map frame ATE "
        f"{loc['ate_rmse_map_frame_m']}, full run on those frames {full_err}; time ratio "
        f"{data['median_seconds_ratio_localisation_over_mapping']:.2f}"
    )


if __name__ == "__main__":
    main()
