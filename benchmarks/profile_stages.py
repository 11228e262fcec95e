"""Where a run's time goes, function by function (issue 17's per-stage profile).

    python benchmarks/profile_stages.py demo              # or tum-fr1-xyz, a folder
    python benchmarks/profile_stages.py demo --top 25
    python benchmarks/profile_stages.py tum-fr1-xyz --config benchmarks/ba_off.yaml
    python benchmarks/profile_stages.py tum-fr1-xyz --tree /path/to/other/tree --tag=-old

Runs ``slam.run`` once under cProfile in this process (default config) and writes the
functions with the most own time (``tottime``), with calls per frame and milliseconds per call
and per frame (and the cumulative milliseconds a frame, callees included), to
``benchmarks/results/profile-<sequence><tag>.json``; ``--config``: a YAML of overrides;
``--tree``: import ``slam`` from another source tree (an old commit's, to see what it did not
spend). cProfile adds overhead to
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
    ap.add_argument("--config", default=None, help="YAML overrides of the default config")
    ap.add_argument("--tree", default=None, help="a source tree to import slam from")
    ap.add_argument("--tag", default="", help="appended to the result's name")
    args = ap.parse_args()
    if args.tree:
        sys.path.insert(0, str(Path(args.tree).resolve()))
    import slam

    logging.basicConfig(level=logging.ERROR)
    cfg = slam.load_config(args.config)
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
        "config": args.config,
        "tree": args.tree,
        "frames": n,
        "profiled_ms_per_frame": round(total, 1),
        "stage_ms_per_frame": res.metrics["stage_ms_per_frame"],
        "top": rows[: args.top],
        "top_cumulative": sorted(rows, key=lambda r: -r["cumulative_ms_per_frame"])[: args.top],
        "machine": machine(),
    }
    path = write_result(f"profile-{Path(args.sequence).name}{args.tag}", out)  # a folder: its name
    print(f"{n} frames, {total:.1f} ms a frame under the profiler")
    print("| function | calls a frame | ms a call | ms a frame |")
    print("|---|---|---|---|")
    for r in rows[: args.top]:
        print(f"| `{r['function']}` | {r['calls_per_frame']} | {r['ms_per_call']} | "
              f"{r['ms_per_frame']} |")  # fmt: skip
    print(f"written: {path}")


if __name__ == "__main__":
    main()
