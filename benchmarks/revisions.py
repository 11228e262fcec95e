"""Several git revisions of the pipeline on one sequence, one fresh process each: where in the
history a figure moved (a bisection by hand over the commits that touched tracking).

    python benchmarks/revisions.py tum-fr1-rpy-500 --revs 2c63699,5ace5e9,18b3f2d,HEAD
    python benchmarks/revisions.py tum-fr1-xyz --revs 2c63699,HEAD --repeats 2 --config my.yaml

Each revision is checked out into a temporary worktree and run with the default config (or
``--config``'s overrides) in its own process, ``--repeats`` times, revisions alternating.
Prints a table (odometry and final ATE, fps whole and tracking + fusion, frames colour joined
depth in, loops) and writes ``benchmarks/results/revisions-<sequence><tag>.json``. Fps figures
compare only within one call (the machine's load changes between calls); nothing else should
run meanwhile.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import tempfile
from pathlib import Path

from common import ROOT, machine, run_in_child, sequence_path, write_result

KEYS = (
    "ate_rmse_odometry_m", "ate_rmse_m", "fps", "fps_tracking_fusion", "colour_frames",
    "loops_accepted", "tracking_failures", "seconds",
)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="demo, a folder under ../shared/datasets, or a path")
    ap.add_argument("--revs", required=True, help="comma-separated git revisions, oldest first")
    ap.add_argument("--config", default="", help="YAML overrides for every revision")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--tag", default="", help="suffix of the result name")
    args = ap.parse_args()
    path = sequence_path(args.sequence)
    config = str(Path(args.config).resolve()) if args.config else ""
    revs = [r.strip() for r in args.revs.split(",") if r.strip()]
    runs: dict[str, list[dict]] = {r: [] for r in revs}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {}
        for rev in revs:
            trees[rev] = Path(tmp) / rev.replace("/", "_")
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(trees[rev]), rev],
                check=True, capture_output=True,
            )  # fmt: skip
        try:
            for i in range(args.repeats):
                for rev in revs if i % 2 == 0 else reversed(revs):
                    runs[rev].append(run_in_child(path, config, KEYS, trees[rev]))
                    print(f"{rev}: {_line(runs[rev][-1])}", flush=True)
        finally:
            for tree in trees.values():
                subprocess.run(
                    ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                    capture_output=True,
                )
    medians = {rev: _medians(r) for rev, r in runs.items()}
    print("\n| revision | odometry / final ATE m | fps whole (t+f) | colour frames | loops |")
    print("|---|---|---|---|---|")
    for rev, m in medians.items():
        print(f"| {rev} | {_line(m)} |".replace(": ", " | ").replace(", ", " | "))
    name = f"revisions-{Path(args.sequence).name}{args.tag}"
    out = write_result(name, {
        "sequence": args.sequence, "config": args.config, "repeats": args.repeats,
        "machine": machine(), "runs": runs, "medians": medians,
    })  # fmt: skip
    print(f"written: {out}")


def _medians(runs: list[dict]) -> dict:
    out = {}
    for k in KEYS:
        vals = [r[k] for r in runs if isinstance(r.get(k), (int, float))]
        out[k] = statistics.median(vals) if vals else None
    return out


def _line(r: dict) -> str:
    def f(k: str, fmt: str) -> str:
        return "-" if r.get(k) is None else fmt.format(r[k])

    return (
        f"{f('ate_rmse_odometry_m', '{:.4f}')} / {f('ate_rmse_m', '{:.4f}')}: "
        f"{f('fps', '{:.1f}')} ({f('fps_tracking_fusion', '{:.1f}')}), "
        f"{f('colour_frames', '{:.0f}')}, {f('loops_accepted', '{:.0f}')}"
    )


if __name__ == "__main__":
    main()
