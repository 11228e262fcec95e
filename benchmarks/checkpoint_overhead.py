"""Time added by checkpoints: runs with `--checkpoint-every N` against runs without, in
alternating fresh processes (whole-run time on a 2-core machine varies by about +-10%, so the
median of the pairs' ratios is reported), and the checkpoints' own time measured inside each
run (`checkpoint_ms` over `seconds` in metrics.json), which does not have that noise.

    python benchmarks/checkpoint_overhead.py demo --every 100 --repeats 3
    python benchmarks/checkpoint_overhead.py tum-fr1-xyz --every 100 --repeats 2
    python benchmarks/checkpoint_overhead.py tum-fr1-xyz --every auto --repeats 3   # the default

Writes benchmarks/results/checkpoint-overhead-<sequence>.json. Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from common import machine, sequence_path, write_result

KEYS = ("seconds", "fps", "checkpoints", "checkpoint_ms", "ate_rmse_m", "frames")


def _run(path: Path, out: Path, every: int | None) -> dict:
    subprocess.run(
        [sys.executable, "-m", "slam.cli", "run", str(path), "--out", str(out), "--overwrite"]
        + ([] if every is None else ["--checkpoint-every", str(every)]),
        check=True,
        capture_output=True,
        text=True,
    )
    m = json.loads((out / "metrics.json").read_text())
    return {k: m.get(k) for k in KEYS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="demo, demo-drift, or a folder under ../shared/datasets")
    parser.add_argument(
        "--every",
        type=lambda v: None if v == "auto" else int(v),
        default=100,
        help="checkpoint interval (frames), or auto (the default of `slam run`)",
    )
    parser.add_argument("--repeats", type=int, default=3, help="pairs of runs")
    args = parser.parse_args()
    path = sequence_path(args.sequence)
    pairs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            order = [("with", args.every), ("without", 0)]
            if i % 2:
                order.reverse()
            pair = {name: _run(path, Path(tmp) / name, every) for name, every in order}
            pair["ratio"] = pair["with"]["seconds"] / pair["without"]["seconds"]
            pair["in_run_fraction"] = pair["with"]["checkpoint_ms"] / 1e3 / pair["with"]["seconds"]
            print(
                f"pair {i + 1}: with {pair['with']['seconds']:.1f} s "
                f"({pair['with']['checkpoints']} checkpoints, {pair['with']['checkpoint_ms']:.0f} ms"
                f" = {pair['in_run_fraction']:.1%}), without {pair['without']['seconds']:.1f} s, "
                f"ratio {pair['ratio'] - 1:+.1%}",
                flush=True,
            )
            pairs.append(pair)
    data = {
        "sequence": args.sequence,
        "every": "auto" if args.every is None else args.every,
        "pairs": pairs,
        "median_added": statistics.median(p["ratio"] for p in pairs) - 1.0,
        "median_in_run_fraction": statistics.median(p["in_run_fraction"] for p in pairs),
        "machine": machine(),
    }
    auto = args.every is None
    out = write_result(f"checkpoint-overhead-{args.sequence}" + ("-auto" if auto else ""), data)
    every = "automatic" if auto else f"every {args.every} frames"
    print(
        f"{out}: checkpoints {every} take {data['median_in_run_fraction']:.1%} "
        f"of the run (median); whole runs {data['median_added']:+.1%} (median of pair ratios)"
    )


if __name__ == "__main__":
    main()
