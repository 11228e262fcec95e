"""Where a run's time goes, function by function (issue 17's per-stage profile).

    python benchmarks/profile_stages.py demo              # or tum-fr1-xyz, a folder
    python benchmarks/profile_stages.py demo --top 25

Runs ``slam.run`` once under cProfile in this process (default config) and writes the
functions with the most own time (``tottime``), with calls per frame and milliseconds per call
and per frame, to ``benchmarks/results/profile-<sequence>.json``. cProfile adds overhead to
Python-level calls, not to the kernels (Open3D, OpenCV, numpy) it times as single calls, so
the kernels' shares are about right and the Python glue's are overstated. Time nothing else
while it runs.
"""

from __future__ import annotations

import argparse
import cProfile
import logging
import pstats
import sys
from pathlib import Path

from common import ROOT, machine, sequence_path, write_result

sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--top", type=int, default=20)
    args = ap.parse_args()
    import slam

    logging.basicConfig(level=logging.ERROR)
    cfg = slam.load_config(None)
    seq = slam.open_sequence(sequence_path(args.sequence), cfg.dataset.layout,
                             cfg.dataset.calibration)  # fmt: skip
    prof = cProfile.Profile()
    prof.enable()
    res = slam.run(seq, cfg)
    prof.disable()
    n = res.metrics["frames"]
    stats = pstats.Stats(prof)
    rows = []
    for (file, line, name), (_, nc, tt, ct, _) in stats.stats.items():  # type: ignore[attr-defined]
        rows.append(
            {
                "function": f"{name} ({file.split('/')[-1]}:{line})",
                "calls_per_frame": round(nc / n, 2),
                "ms_per_call": round(1e3 * tt / max(nc, 1), 3),
                "ms_per_frame": round(1e3 * tt / n, 2),
                "cumulative_ms_per_frame": round(1e3 * ct / n, 2),
            }
        )
    rows.sort(key=lambda r: -r["ms_per_frame"])
    total = sum(r["ms_per_frame"] for r in rows)
    out = {
        "sequence": args.sequence,
        "frames": n,
        "profiled_ms_per_frame": round(total, 1),
        "stage_ms_per_frame": res.metrics["stage_ms_per_frame"],
        "top": rows[: args.top],
        "machine": machine(),
    }
    path = write_result(f"profile-{Path(args.sequence).name}", out)  # a folder: its name
    print(f"{n} frames, {total:.1f} ms a frame under the profiler")
    print("| function | calls a frame | ms a call | ms a frame |")
    print("|---|---|---|---|")
    for r in rows[: args.top]:
        print(f"| `{r['function']}` | {r['calls_per_frame']} | {r['ms_per_call']} | "
              f"{r['ms_per_frame']} |")  # fmt: skip
    print(f"written: {path}")


if __name__ == "__main__":
    main()
