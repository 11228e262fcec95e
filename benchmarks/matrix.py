"""The scene matrix: every shared real sequence and every synthetic scene kind (two speeds,
several seeds), one table that judges a tracking or mapping change.

    python benchmarks/matrix.py                      # the full matrix, this tree
    python benchmarks/matrix.py --tree /path/to/old --tag old
    python benchmarks/matrix.py --compare benchmarks/results/matrix-old.json \\
                                          benchmarks/results/matrix.json
    python benchmarks/matrix.py --small              # the CI version (tiny synthetic rows)

Each row runs in a fresh process (default config; ``--tree``: import ``slam`` from another
source tree, e.g. a worktree of main, so old and new run the very same sequences). A row
records odometry and final ATE (RMSE, SE(3)-aligned), the per-frame step error of odometry
(translation error of each frame-to-frame motion against ground truth: median and worst, and
their ratio), lost frames, loops and fps. One row per kind is also rendered exact (no sensor
noise: ``EXACT``), with colour not synchronised with depth (``UNSYNCED``), and as a hand-held
Kinect v1 records it (``HANDHELD``: a recorded hand's motion, rolling shutter, blur, exposure,
Kinect depth), and each real sequence recorded at video rate runs again on every third frame
(``-x3``: real motion three times as fast). ``colour_frames`` counts the frames colour
joined depth in (a check fired, or depth was blind), ``check_frames`` those whose estimate on
depth alone broke a motion check (``TrackingStatus.motion_check``). Synthetic sequences are generated once into the cache
folder (``$SLAM_CACHE_DIR``/matrix). Writes ``benchmarks/results/matrix[-TAG].json`` and prints a
Markdown table.

``--compare OLD NEW`` prints, per row, the change of odometry ATE, final ATE and worst step
error, flagged when it exceeds the row's run-to-run spread (``--repeats`` > 1 measures it:
the range over repeats; ``--spread FILE ...`` adds the ranges of other such runs, the largest
counting; otherwise 10% + 0.5 mm is assumed) in both runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from common import ROOT, SHARED, machine, write_result

#: Scene kinds, speeds and seeds of the full matrix (``room`` is the demo's furnished room).
KINDS = ("room", "wall", "corridor", "hall", "desk")
SPEEDS = (1.0, 2.0)
SEEDS = (0, 1)
#: Rows rendered without the sensor model (exact depth, no dropouts, clean colour): synthetic
#: data a user brings need not be noisy, and exact depth takes away the noise that hides a
#: term's weighting (corridor-x2-s1 drifted 0.29 m on exact depth, session 16). One fast row
#: per kind, seed 0, and that corridor: (kind, speed, seed).
EXACT = tuple((kind, 2.0, 0) for kind in KINDS) + (("corridor", 2.0, 1),)
#: Rows whose colour camera is not synchronised with depth: each colour image taken within
#: UNSYNCED_MS of its depth image, as TUM fr1 / fr2's Kinect (up to 17 ms): on a fast camera
#: colour and depth then see from poses millimetres and tenths of a degree apart. One fast row
#: per kind, seed 0: (kind, speed, seed); row names end in ``-c<ms>``.
UNSYNCED = tuple((kind, 2.0, 0) for kind in KINDS)
UNSYNCED_MS = 15.0
#: Rows that move and look like a hand-held Kinect v1 (``SynthConfig.handheld`` and
#: ``kinect``: a recorded hand's motion on the kind's path; rolling shutter, motion blur, auto
#: exposure, projector shadows, ragged edges, correlated depth noise; colour UNSYNCED_MS off
#: depth): the real conditions at every scene kind. Kind -> recording; seeds start 7 s apart
#: in it. Row names: ``<kind>-hh-s<seed>``.
HANDHELD = {
    "room": "fr1_room", "wall": "fr1_360", "corridor": "fr1_teddy", "hall": "fr1_plant",
    "desk": "fr1_desk2",
}  # fmt: skip
HANDHELD_SEEDS = (0, 1)
FRAMES = 240
#: Real sequences recorded at video rate run a second time on every REAL_STRIDE-th frame.
REAL_STRIDE = 3
#: A change within this of a row's value is noise when the spread was not measured.
DEFAULT_SPREAD = (0.10, 0.0005)


@dataclass
class Row:
    name: str
    path: Path
    synthetic: bool


def synthetic_rows(
    frames: int,
    kinds,
    speeds,
    seeds,
    half: bool = False,
    exact=(),
    only: str = "",
    unsynced=(),
    drift_bias: float = 0.0,
    handheld=(),
) -> list[Row]:
    """Every kind x speed x seed, then the ``exact`` (kind, speed, seed) rows without noise and
    the ``unsynced`` ones with colour taken up to ``UNSYNCED_MS`` off the depth; ``only``:
    comma-separated substrings of the row names to keep (the others are not generated);
    ``drift_bias``: every row's depth distorted radially, as an uncalibrated Kinect's
    (``SynthConfig.drift_bias``; the names end in ``-d`` and the bias in thousandths);
    ``handheld``: (kind, seed) rows as a hand-held Kinect v1 records them (:data:`HANDHELD`)."""
    from slam.demo import cache_dir
    from slam.synthetic import SynthConfig, generate_sequence, is_complete

    combos = [(k, sp, se, True, 0.0) for k in kinds for sp in speeds for se in seeds]
    combos += [(k, sp, se, False, 0.0) for k, sp, se in exact]
    combos += [(k, sp, se, True, UNSYNCED_MS) for k, sp, se in unsynced]
    combos += [(k, 1.0, se, True, UNSYNCED_MS, HANDHELD[k]) for k, se in handheld]
    rows = []
    for kind, speed, seed, noise, offset_ms, *recorded in combos:
        hand = recorded[0] if recorded else ""
        if hand:
            name = f"{kind}-hh-s{seed}" + ("-half" if half else "")
        else:
            name = f"{kind}-x{speed:g}-s{seed}" + ("-half" if half else "")
            name += ("" if noise else "-exact") + (f"-c{offset_ms:g}" if offset_ms else "")
        name += f"-d{1000 * drift_bias:g}" if drift_bias else ""
        if only and not any(s in name for s in only.split(",")):
            continue
        kw = dict(frames=frames, scene=kind, speed=speed, seed=seed, loop=kind == "room")
        kw["noise"] = noise
        kw["color_offset_ms"] = offset_ms
        kw["drift_bias"] = drift_bias
        kw.update(handheld=hand, kinect=bool(hand))
        cfg = SynthConfig.half_resolution(**kw) if half else SynthConfig(**kw)
        # v2 of the unsynchronised rows: the colour camera at its own steady rate (v1 drew
        # each frame's offset independently)
        path = cache_dir() / "matrix" / f"{name}-{frames}-v{2 if offset_ms else 1}"
        if not is_complete(path):
            print(f"generating {name} ({frames} frames) into {path}", file=sys.stderr)
            generate_sequence(path, cfg)
        rows.append(Row(name, path, True))
    return rows


def real_rows() -> list[Row]:
    """Every shared real sequence, then each one recorded at video rate (median frame interval
    under 50 ms) again at ``REAL_STRIDE`` times its speed: every ``REAL_STRIDE``-th frame
    (``<name>-x3``), real motion faster than any shared recording."""
    if not SHARED.is_dir():
        return []
    seqs = [p for p in sorted(SHARED.iterdir()) if p.is_dir() and (p / "groundtruth.txt").is_file()]
    rows = [Row(p.name, p, False) for p in seqs]
    for p in seqs:
        if _median_interval_s(p / "depth.txt") < 0.05:
            rows.append(Row(f"{p.name}-x{REAL_STRIDE}", strided_copy(p, REAL_STRIDE), False))
    return rows


def _list_lines(path: Path) -> tuple[list[str], list[str]]:
    """(comment lines, entry lines) of a TUM list file (``timestamp path`` per line)."""
    lines = path.read_text().splitlines()
    return [s for s in lines if s.startswith("#")], [s for s in lines if s.strip() and s[0] != "#"]


def _median_interval_s(list_file: Path) -> float:
    if not list_file.is_file():
        return float("inf")
    stamps = sorted(float(s.split()[0]) for s in _list_lines(list_file)[1])
    gaps = sorted(b - a for a, b in zip(stamps, stamps[1:]))
    return gaps[len(gaps) // 2] if gaps else float("inf")


def strided_copy(seq: Path, stride: int) -> Path:
    """A copy of a TUM-layout sequence with every ``stride``-th entry of ``rgb.txt`` and
    ``depth.txt`` (the first kept); every other file and folder is a symlink to the original.
    Made once, in the cache folder."""
    from slam.demo import cache_dir

    out = cache_dir() / "matrix" / "real" / f"{seq.name}-x{stride}"
    if (out / "depth.txt").is_file():
        return out
    tmp = out.with_name(out.name + ".tmp")
    tmp.mkdir(parents=True, exist_ok=True)
    for item in seq.iterdir():
        link = tmp / item.name
        if item.name in ("rgb.txt", "depth.txt"):
            comments, entries = _list_lines(item)
            link.write_text("\n".join(comments + entries[::stride]) + "\n")
        elif not link.exists():
            link.symlink_to(item.resolve())
    tmp.rename(out)
    return out


# runs in a fresh process, importing slam from the tree under test: numpy and slam only
_CHILD = r"""
import json, logging, resource, sys, time
import numpy as np
import slam
from slam.trajectory import read_tum
logging.basicConfig(level=logging.ERROR)
path = sys.argv[1]
cfg = slam.load_config(None)
seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
t0 = time.perf_counter()
res = slam.run(seq, cfg)
wall = time.perf_counter() - t0
m = res.metrics
gt = read_tum(path + "/groundtruth.txt")
est = res.odometry
j = np.searchsorted(gt.timestamps, est.timestamps).clip(1, len(gt.timestamps) - 1)
j = np.where(np.abs(gt.timestamps[j - 1] - est.timestamps) < np.abs(gt.timestamps[j] - est.timestamps), j - 1, j)
ok = np.abs(gt.timestamps[j] - est.timestamps) < 0.02
E, G = est.poses[ok], gt.poses[j[ok]]
dE = np.linalg.inv(E[:-1]) @ E[1:]
dG = np.linalg.inv(G[:-1]) @ G[1:]
err = np.linalg.norm((np.linalg.inv(dG) @ dE)[:, :3, 3], axis=1)
true_step = np.linalg.norm(dG[:, :3, 3], axis=1)
worst = int(np.argmax(err)) if len(err) else -1
out = {k: m.get(k) for k in ("frames", "ate_rmse_odometry_m", "ate_rmse_m", "fps",
       "fps_tracking_fusion", "tracking_failures", "loops_accepted", "keyframes")}
out.update(
    seconds=wall,
    step_err_median_m=float(np.median(err)) if len(err) else None,
    step_err_max_m=float(err.max()) if len(err) else None,
    step_err_worst_frame=int(np.flatnonzero(ok)[worst + 1]) if len(err) else None,
    true_step_median_m=float(np.median(true_step)) if len(err) else None,
    colour_frames=sum(1 for s in res.tracking if getattr(s, "photometric", False)),
    check_frames=sum(1 for s in res.tracking if getattr(s, "motion_check", "")),
    peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
)
print(json.dumps(out))
"""


def run_row(row: Row, tree: Path | None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)} if tree is not None else None
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(row.path)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tree or ROOT,
    )
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-3:]
        return {"error": " | ".join(tail)}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def summarise(runs: list[dict]) -> dict:
    """A row's value (median over repeats) and its run-to-run range."""
    good = [r for r in runs if "error" not in r]
    if not good:
        return {"error": runs[0].get("error"), "repeats": len(runs)}
    out: dict = {"repeats": len(good)}
    for key in good[0]:
        vals = [r[key] for r in good if r.get(key) is not None]
        if vals and isinstance(vals[0], (int, float)):
            vals.sort()
            out[key] = vals[len(vals) // 2]
            if len(vals) > 1:
                out[f"{key}_range"] = vals[-1] - vals[0]
    ratio = out.get("step_err_max_m"), out.get("step_err_median_m")
    if ratio[0] is not None and ratio[1]:
        out["step_err_ratio"] = ratio[0] / ratio[1]
    return out


def _f(v, scale=1.0, fmt="{:.4f}") -> str:
    return "-" if v is None else fmt.format(v * scale)


def table(rows: dict[str, dict]) -> str:
    head = (
        "| row | odometry ATE m | final ATE m | step error median / worst mm (ratio) "
        "| lost | colour | loops | fps |\n|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for name, r in rows.items():
        if "error" in r:
            lines.append(f"| {name} | failed: {r['error']} | | | | | | |")
            continue
        steps = (
            f"{_f(r.get('step_err_median_m'), 1e3, '{:.1f}')} / "
            f"{_f(r.get('step_err_max_m'), 1e3, '{:.1f}')} "
            f"({_f(r.get('step_err_ratio'), 1, '{:.1f}')}x)"
        )
        lines.append(
            f"| {name} | {_f(r.get('ate_rmse_odometry_m'))} | {_f(r.get('ate_rmse_m'))} | {steps} "
            f"| {r.get('tracking_failures')} | {r.get('colour_frames', '-')} "
            f"| {r.get('loops_accepted')} "
            f"| {_f(r.get('fps'), 1, '{:.1f}')} |"
        )
    return head + "\n".join(lines) + "\n"


def _spread(r: dict, key: str, known: float | None = None) -> float:
    """A row's spread in ``key``: the range measured over its repeats, or ``known`` (measured
    in other runs: ``--spread``), the larger of the two; else the assumed DEFAULT_SPREAD."""
    measured = [v for v in (r.get(f"{key}_range"), known) if v is not None]
    if measured:
        return max(measured)
    rel, floor = DEFAULT_SPREAD
    return rel * abs(r.get(key) or 0.0) + floor


def measured_spreads(results: list[dict]) -> dict[str, dict[str, float]]:
    """Per row and column, the largest range over repeats in these result files (written
    with ``--repeats`` > 1): the run-to-run spread ``--compare`` then judges changes by."""
    out: dict[str, dict[str, float]] = {}
    for res in results:
        for name, r in res.get("rows", {}).items():
            for k, v in r.items():
                if k.endswith("_range") and isinstance(v, (int, float)):
                    key = k[: -len("_range")]
                    out.setdefault(name, {})[key] = max(v, out.get(name, {}).get(key, 0.0))
    return out


def compare(
    old: dict, new: dict, spreads: dict[str, dict[str, float]] | None = None
) -> tuple[str, int]:
    """Per-row changes of the accuracy columns; a change beyond both runs' spreads is flagged
    (``spreads``: ranges measured in other runs, :func:`measured_spreads`). Returns the text
    and the number of rows that got worse beyond their spread."""
    keys = ("ate_rmse_odometry_m", "ate_rmse_m", "step_err_max_m")
    spreads = spreads or {}
    lines = ["| row | " + " | ".join(keys) + " | fps |", "|---" * (len(keys) + 2) + "|"]
    worse = 0
    for name in list(old["rows"]) + [n for n in new["rows"] if n not in old["rows"]]:
        a, b = old["rows"].get(name), new["rows"].get(name)
        if a is None or b is None or "error" in a or "error" in b:
            lines.append(f"| {name} | (missing or failed in one of the two) |")
            continue
        cells, bad = [], False
        for k in keys:
            va, vb = a.get(k), b.get(k)
            if va is None or vb is None:
                cells.append("-")
                continue
            known = spreads.get(name, {}).get(k)
            tol = max(_spread(a, k, known), _spread(b, k, known))
            flag = " **worse**" if vb - va > tol else (" better" if va - vb > tol else "")
            bad |= vb - va > tol
            cells.append(f"{va:.4f} -> {vb:.4f}{flag}")
        worse += bad
        fa, fb = a.get("fps"), b.get("fps")
        fps = f"{fa:.1f} -> {fb:.1f}" if fa and fb else "-"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {fps} |")
    return "\n".join(lines) + "\n", worse


def _commit(tree: Path) -> str:
    """The short commit of ``tree`` (its working tree may differ: the run says which code)."""
    out = subprocess.run(
        ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return out.stdout.strip() or "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", type=Path, default=None, help="source tree to import slam from")
    ap.add_argument("--tag", default="", help="suffix of the result file")
    ap.add_argument("--repeats", type=int, default=1, help="runs per row (spread when > 1)")
    ap.add_argument("--frames", type=int, default=FRAMES, help="frames of each synthetic row")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    ap.add_argument("--speeds", default=",".join(map(str, SPEEDS)))
    ap.add_argument("--no-real", action="store_true", help="synthetic rows only")
    ap.add_argument("--no-exact", action="store_true", help="without the exact-depth rows")
    ap.add_argument(
        "--no-unsynced", action="store_true", help="without the unsynchronised-colour rows"
    )
    ap.add_argument(
        "--no-handheld", action="store_true", help="without the hand-held Kinect rows"
    )
    ap.add_argument("--only", default="", help="comma-separated substrings: run matching rows")
    ap.add_argument(
        "--drift-bias", type=float, default=0.0,
        help="radial depth distortion of every synthetic row (e.g. 0.006; rows named -d6)",
    )  # fmt: skip
    ap.add_argument("--small", action="store_true", help="CI version: 2 tiny synthetic rows")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default results/)")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("OLD", "NEW"))
    ap.add_argument(
        "--spread", nargs="+", type=Path, default=[], metavar="FILE",
        help="with --compare: result files of --repeats runs whose ranges are the rows' spread",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.compare:
        old, new = (json.loads(p.read_text()) for p in args.compare)
        spreads = measured_spreads([json.loads(p.read_text()) for p in args.spread])
        text, worse = compare(old, new, spreads)
        print(text + f"\n{worse} row(s) worse beyond their spread")
        return 0
    if args.small:
        rows = synthetic_rows(40, ("wall", "corridor"), (1.0,), (0,), half=True)
    else:
        rows = synthetic_rows(
            args.frames,
            args.kinds.split(","),
            [float(s) for s in args.speeds.split(",")],
            [int(s) for s in args.seeds.split(",")],
            exact=() if args.no_exact else [e for e in EXACT if e[0] in args.kinds.split(",")],
            only=args.only,
            unsynced=()
            if args.no_unsynced
            else [e for e in UNSYNCED if e[0] in args.kinds.split(",")],
            drift_bias=args.drift_bias,
            handheld=()
            if args.no_handheld
            else [(k, se) for k in args.kinds.split(",") if k in HANDHELD for se in HANDHELD_SEEDS],
        )
        rows = ([] if args.no_real else real_rows()) + rows
    if args.only:
        rows = [r for r in rows if any(s in r.name for s in args.only.split(","))]
    results: dict[str, dict] = {}
    t0 = time.perf_counter()
    for row in rows:
        runs = [run_row(row, args.tree) for _ in range(args.repeats)]
        results[row.name] = summarise(runs)
        r = results[row.name]
        print(
            f"{row.name}: odometry {_f(r.get('ate_rmse_odometry_m'))} final "
            f"{_f(r.get('ate_rmse_m'))} worst step {_f(r.get('step_err_max_m'), 1e3, '{:.1f}')} "
            f"mm ({_f(r.get('step_err_ratio'), 1, '{:.1f}')}x median), "
            f"{_f(r.get('fps'), 1, '{:.1f}')} fps {r.get('error', '')}",
            file=sys.stderr,
        )
    data = {
        "tree": str(args.tree or ROOT),
        "commit": _commit(Path(args.tree or ROOT)),
        "repeats": args.repeats,
        "seconds": round(time.perf_counter() - t0, 1),
        "machine": machine(),
        "rows": results,
    }
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(data, indent=2) + "\n")
        out = args.out
    else:
        out = write_result("matrix" + (f"-{args.tag}" if args.tag else ""), data)
    print(table(results) + f"\nwritten: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
