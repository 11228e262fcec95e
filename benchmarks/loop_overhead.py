"""Time added by loop handling: whole-run time with the default config against the same sequence
with loop closure off and a single TSDF, in alternating fresh processes, and the median of the
pairwise ratios (whole-run time on a 2-core machine varies by about +-10% from run to run, so
one pair is not a measurement).

    python benchmarks/loop_overhead.py demo-drift --repeats 3
    python benchmarks/loop_overhead.py 7scenes-300 --repeats 2

Writes benchmarks/results/loop-overhead-<sequence>.json. Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from common import machine, run_in_child, sequence_path, write_result

NO_LOOP = "loop: {enabled: false}\nmapping: {submap_keyframes: 0}\n"

KEYS = (
    "seconds", "fps", "fps_tracking_fusion", "ate_rmse_m", "ate_rmse_odometry_m",
    "loops_accepted", "loops_rejected", "submaps", "stage_ms_total",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="demo, demo-drift, or a folder under ../shared/datasets")
    parser.add_argument("--repeats", type=int, default=3, help="pairs of runs")
    args = parser.parse_args()
    path = sequence_path(args.sequence)
    with tempfile.TemporaryDirectory() as tmp:
        no_loop = Path(tmp) / "noloop.yaml"
        no_loop.write_text(NO_LOOP)
        pairs = []
        for i in range(args.repeats):
            # alternate which run goes first, so a slow drift of the machine cancels out
            order = [("with", ""), ("without", str(no_loop))]
            if i % 2:
                order.reverse()
            pair = {name: run_in_child(path, cfg, KEYS) for name, cfg in order}
            pair["ratio"] = pair["with"]["seconds"] / pair["without"]["seconds"]
            print(
                f"pair {i + 1}: with {pair['with']['seconds']:.1f} s, "
                f"without {pair['without']['seconds']:.1f} s, added {pair['ratio'] - 1:+.1%}",
                flush=True,
            )
            pairs.append(pair)
    ratios = [p["ratio"] for p in pairs]
    data = {
        "sequence": args.sequence,
        "without_config": NO_LOOP,
        "pairs": pairs,
        "median_added": statistics.median(ratios) - 1.0,
        "seconds_with_median": statistics.median(p["with"]["seconds"] for p in pairs),
        "seconds_without_median": statistics.median(p["without"]["seconds"] for p in pairs),
        "machine": machine(),
    }
    out = write_result(f"loop-overhead-{args.sequence}", data)
    print(f"{out}: loop handling adds {data['median_added']:+.1%} (median of {len(pairs)} pairs)")


if __name__ == "__main__":
    main()
