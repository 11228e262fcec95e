"""Two versions or configurations of the pipeline on one sequence, run in alternating fresh
processes (whole-run time on a 2-core machine varies by about +-10%, so single runs do not
compare; the median of the pairs' ratios does).

    # tracking + fusion speed of the working tree against an earlier commit
    python benchmarks/alternate.py tum-fr1-xyz --a-rev 33bb516 --repeats 3
    # bundle adjustment on (default) against off, same code
    python benchmarks/alternate.py tum-fr1-xyz --a-config ba_off.yaml --repeats 3
    # the same code with one BLAS thread in arm B's processes
    python benchmarks/alternate.py tum-fr1-xyz --b-env OPENBLAS_NUM_THREADS=1

Arm A is ``--a-rev`` (a git revision, checked out into a temporary worktree) with ``--a-config``;
arm B the working tree with ``--b-config``; ``--a-env``/``--b-env`` set variables of one arm's
processes. Writes benchmarks/results/alternate-<name>.json with
each run's seconds, fps, fps of tracking + fusion and ATE, and the medians of the B/A ratios.
Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import tempfile
from pathlib import Path

from common import ROOT, machine, run_in_child, sequence_path, write_result

KEYS = (
    "seconds", "fps", "fps_tracking_fusion", "ate_rmse_m", "ate_rmse_odometry_m",
    "ate_rmse_pose_graph_m", "frames",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="demo, demo-drift, or a folder under ../shared/datasets")
    parser.add_argument("--a-rev", default=None, help="git revision of arm A (default: this tree)")
    parser.add_argument("--a-config", default="", help="YAML config of arm A")
    parser.add_argument("--b-config", default="", help="YAML config of arm B (this tree)")
    parser.add_argument("--a-env", action="append", default=[], metavar="KEY=VALUE",
                        help="environment variable of arm A's processes (repeatable)")
    parser.add_argument("--b-env", action="append", default=[], metavar="KEY=VALUE",
                        help="environment variable of arm B's processes (repeatable)")
    parser.add_argument("--repeats", type=int, default=3, help="pairs of runs")
    parser.add_argument("--name", default=None, help="result name (default from the arms)")
    args = parser.parse_args()
    path = sequence_path(args.sequence)
    with tempfile.TemporaryDirectory() as tmp:
        tree_a = ROOT
        if args.a_rev:
            tree_a = Path(tmp) / "a"
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree_a), args.a_rev],
                check=True,
                capture_output=True,
            )
        arms = {
            "a": (tree_a, str(Path(args.a_config).resolve()) if args.a_config else ""),
            "b": (ROOT, str(Path(args.b_config).resolve()) if args.b_config else ""),
        }
        envs = {"a": _env(args.a_env), "b": _env(args.b_env)}
        pairs = []
        try:
            for i in range(args.repeats):
                order = ["a", "b"] if i % 2 == 0 else ["b", "a"]
                pair = {
                    arm: run_in_child(path, arms[arm][1], KEYS, arms[arm][0], envs[arm])
                    for arm in order
                }
                pair["seconds_ratio"] = pair["b"]["seconds"] / pair["a"]["seconds"]
                pair["fps_tf_ratio"] = (
                    pair["b"]["fps_tracking_fusion"] / pair["a"]["fps_tracking_fusion"]
                )
                print(
                    f"pair {i + 1}: A {pair['a']['seconds']:.1f} s, "
                    f"{pair['a']['fps_tracking_fusion']:.1f} fps t+f, ATE {pair['a']['ate_rmse_m']}"
                    f" | B {pair['b']['seconds']:.1f} s, {pair['b']['fps_tracking_fusion']:.1f} "
                    f"fps t+f, ATE {pair['b']['ate_rmse_m']}",
                    flush=True,
                )
                pairs.append(pair)
        finally:
            if args.a_rev:
                subprocess.run(
                    ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree_a)],
                    capture_output=True,
                )
    data = {
        "sequence": args.sequence,
        "a": {"rev": args.a_rev or "working tree", "config": args.a_config, "env": args.a_env},
        "b": {"rev": "working tree", "config": args.b_config, "env": args.b_env},
        "pairs": pairs,
        "median_seconds_ratio_b_over_a": statistics.median(p["seconds_ratio"] for p in pairs),
        "median_fps_tf_ratio_b_over_a": statistics.median(p["fps_tf_ratio"] for p in pairs),
        "machine": machine(),
    }
    seq_name = Path(args.sequence).name  # a folder: its name
    name = args.name or f"{seq_name}-{args.a_rev or Path(args.a_config).stem or 'a'}"
    out = write_result(f"alternate-{name}", data)
    print(
        f"{out}: B/A whole-run time {data['median_seconds_ratio_b_over_a']:.3f}, "
        f"tracking+fusion fps {data['median_fps_tf_ratio_b_over_a']:.3f} (medians of "
        f"{len(pairs)} pairs)"
    )


def _env(pairs: list[str]) -> dict[str, str]:
    out = {}
    for kv in pairs:
        key, sep, value = kv.partition("=")
        if not sep or not key:
            raise SystemExit(f"--a-env/--b-env take KEY=VALUE, got {kv!r}")
        out[key] = value
    return out


if __name__ == "__main__":
    main()
