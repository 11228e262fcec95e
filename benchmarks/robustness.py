"""Damaged copies of a sequence, each run through `slam run`, against the clean run.

    python benchmarks/robustness.py demo
    python benchmarks/robustness.py tum-fr3-cabinet-kf58 --only blackout,teleport

Scenarios (frame numbers scale with the sequence's length N):
- clean: the sequence as it is.
- blackout: 15 frames mid-sequence with zero depth and black colour (a covered lens).
- teleport: at frame k the camera jumps back B frames (B = min(200, 2N/3)) and goes on from
  there, with no time gap (frames [0, k) + [k - B, N), evenly retimed).
- corrupt: 5 unreadable frames (depth truncated, random bytes, zero bytes, half size; colour
  truncated).
- gap: 10 frames missing from the lists (a time gap) a third of the way in.
- depth_scale: calibration depth_scale 1000x too large (the run must refuse: exit 2).
- resume: `--checkpoint-every C` (C = N/3), kill -9 after the first checkpoint is written, then
  `slam run --resume`; compared with an uninterrupted run.

Each run is a `slam run` process; ATE is over the poses it wrote. Checks (from the robustness
issue): blackout/teleport/corrupt ATE <= 1.5x clean + 3 mm; resume <= 1.2x uninterrupted + 1 mm.
Writes benchmarks/results/robustness-<sequence>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import machine, sequence_path, write_result

import slam
from slam.run_folder import CHECKPOINT_DIR
from slam.run_folder.checkpoint import STATE_FILE
from slam.synthetic.damage import Damage, damage_sequence

SLAM = [sys.executable, "-m", "slam.cli"]


def run_slam(args: list[str], timeout: float = 3600) -> tuple[int, str, float]:
    t0 = time.perf_counter()
    p = subprocess.run(SLAM + args, capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stderr[-3000:] + p.stdout[-2000:], time.perf_counter() - t0


def metrics_of(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


def summary(m: dict) -> dict:
    keys = (
        "frames",
        "frames_tracked",
        "frames_in_trajectory",
        "frames_skipped",
        "relocalisations",
        "loops_accepted",
        "ate_rmse_m",
        "ate_rmse_odometry_m",
        "matched_poses",
        "seconds",
        "checkpoints",
        "checkpoint_ms",
    )
    out = {k: m.get(k) for k in keys}
    out["lost_frames"] = m.get("lost_frames")
    out["map_segments"] = len(m.get("map_segments", []))
    out["segment_joins"] = len(m.get("segment_joins", []))
    return out


def scenarios(n: int) -> dict[str, Damage]:
    back = min(200, (2 * n) // 3)
    k = back + (n - back) // 2
    mid = n // 2
    third = n // 3
    return {
        "blackout": Damage(blackout=range(mid - 7, mid + 8)),
        "teleport": Damage(frames=[*range(k), *range(k - back, n)], retime=True),
        "corrupt": Damage(
            corrupt={
                n // 6: "truncate",
                2 * n // 6: "random",
                3 * n // 6: "empty",
                4 * n // 6: "wrong_size",
                5 * n // 6: "color:truncate",
            }
        ),
        "gap": Damage(frames=[*range(third), *range(third + 10, n)]),
        "depth_scale": Damage(depth_scale_factor=1000.0),
    }


def run_resume(seq: Path, work: Path, every: int) -> dict:
    out = work / "resume"
    proc = subprocess.Popen(
        SLAM + ["run", str(seq), "--out", str(out), "--checkpoint-every", str(every)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    state = out / CHECKPOINT_DIR / STATE_FILE
    t0 = time.perf_counter()
    while not state.exists() and proc.poll() is None:
        time.sleep(0.2)
    killed_after = time.perf_counter() - t0
    if proc.poll() is not None:
        return {"error": f"run ended (exit {proc.returncode}) before its first checkpoint"}
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    code, log_text, secs = run_slam(["run", "--resume", str(out)])
    res = {"exit_code": code, "killed_after_s": round(killed_after, 1), "resume_seconds": secs}
    if code == 0:
        res.update(summary(metrics_of(out)))
    else:
        res["log"] = log_text
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="demo, demo-drift, or a folder under ../shared/datasets")
    parser.add_argument("--only", default=None, help="comma-separated scenario names")
    parser.add_argument("--keep", default=None, help="keep the damaged copies and runs here")
    args = parser.parse_args()
    src = sequence_path(args.sequence)
    n = len(slam.open_sequence(src))
    work = Path(args.keep or tempfile.mkdtemp(prefix="slam-robust-"))
    work.mkdir(parents=True, exist_ok=True)
    only = None if args.only is None else set(args.only.split(","))
    results: dict[str, dict] = {}

    def want(name: str) -> bool:
        return only is None or name in only

    clean = None
    if want("clean") or only is None or only - {"depth_scale"}:
        code, text, secs = run_slam(["run", str(src), "--out", str(work / "clean"), "--overwrite"])
        results["clean"] = {"exit_code": code, "wall_s": round(secs, 1)}
        if code == 0:
            clean = metrics_of(work / "clean")
            results["clean"].update(summary(clean))
        print("clean", results["clean"], flush=True)
    for name, dmg in scenarios(n).items():
        if not want(name):
            continue
        seq = damage_sequence(src, work / f"seq-{name}", dmg)
        code, text, secs = run_slam(["run", str(seq), "--out", str(work / name), "--overwrite"])
        res: dict = {"exit_code": code, "wall_s": round(secs, 1)}
        if code == 0:
            res.update(summary(metrics_of(work / name)))
        else:
            res["message"] = text.strip().splitlines()[-3:] if text.strip() else []
        if clean and res.get("ate_rmse_m") is not None and clean.get("ate_rmse_m"):
            bound = 1.5 * clean["ate_rmse_m"] + 0.003
            res["ate_bound_m"] = round(bound, 4)
            res["ate_ok"] = res["ate_rmse_m"] <= bound
        results[name] = res
        print(name, res, flush=True)
    if want("resume"):
        every = max(n // 3, 1)
        res = run_resume(src, work, every)
        if clean and res.get("ate_rmse_m") is not None:
            bound = 1.2 * clean["ate_rmse_m"] + 0.001
            res["ate_bound_m"] = round(bound, 4)
            res["ate_ok"] = res["ate_rmse_m"] <= bound
            res["frames_written_ok"] = res.get("frames_tracked") == clean.get("frames_tracked")
        results["resume"] = res
        print("resume", res, flush=True)
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)
    tag = "" if only is None else "-" + "-".join(sorted(only))
    out = write_result(
        f"robustness-{Path(args.sequence).name}{tag}",
        {"sequence": args.sequence, "frames": n, "results": results, "machine": machine()},
    )
    print(out)


if __name__ == "__main__":
    main()
