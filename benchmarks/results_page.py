"""docs/results.md and the README's results table: today's default on every shared sequence and
the scene matrix, from one scene-matrix run.

    python benchmarks/results_page.py --run            # run the matrix (~45 min), then write
    python benchmarks/results_page.py --matrix benchmarks/results/matrix-s60-head.json

``--run`` runs ``benchmarks/matrix.py --tag results`` (every shared real sequence, again at
three times the speed, and every synthetic row) in this tree and writes the page from its
result; ``--matrix FILE`` writes it from a result already made. The page states the date, the
machine and the commit, and per row odometry / final ATE, worst step error, fps, peak memory and
the frames colour joined depth in; the README's table (between its ``results`` markers) gets the
real recordings, one figure each, beside the reference figures of :data:`REFERENCE`. Nothing
else should run meanwhile when the fps matter.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from common import ROOT

PAGE = ROOT / "docs" / "results.md"
README = ROOT / "README.md"
RESULTS = ROOT / "benchmarks" / "results"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
#: the README's reference columns: Open3D's dense SLAM on the same frames
#: (``benchmarks/open3d_baseline.py``, 1 cm voxels) and published figures
REFERENCE = {
    "tum-fr1-xyz": ("0.0220 m", "DVO-SLAM ~0.011 m, KinectFusion ~0.026 m"),
    "tum-fr1-rpy-500": ("-", "-"),
    "tum-fr3-cabinet-kf58": ("0.526 m", "-"),
    "7scenes-300": ("-", "-"),
}


def _commit() -> str:
    out = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return out.stdout.strip() or "unknown"


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{1000 * v:.1f}"


def _num(v: float | None, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def _row(name: str, r: dict) -> str:
    return (
        f"| `{name}` | {r.get('frames', '-')} | {_mm(r.get('ate_rmse_odometry_m'))} / "
        f"**{_mm(r.get('ate_rmse_m'))}** | {_mm(r.get('step_err_max_m'))} | "
        f"{_num(r.get('fps'))} | {_num(r.get('peak_rss_mb'), '{:.0f}')} | "
        f"{r.get('colour_frames', '-')} | {r.get('tracking_failures', '-')} |"
    )


def readme_table(matrix: dict) -> str:
    """The README's table: each real recording at its own speed (no ``-x3`` rows)."""
    lines = [
        "| sequence | frames | odometry / final ATE | fps | peak MB | Open3D dense SLAM (1 cm) "
        "| published |",
        "|---|---:|---|---:|---:|---|---|",
    ]
    for name, r in matrix["rows"].items():
        if name not in REFERENCE:
            continue
        o3d, published = REFERENCE[name]
        odo, final = r.get("ate_rmse_odometry_m"), r.get("ate_rmse_m")
        lines.append(
            f"| `{name}` | {r.get('frames', '-')} | {_num(odo, '{:.4f}')} / "
            f"**{_num(final, '{:.4f}')} m** | {_num(r.get('fps'))} | "
            f"{_num(r.get('peak_rss_mb'), '{:.0f}')} | {o3d} | {published} |"
        )
    return "\n".join(lines)


def with_readme_table(readme: str, table: str) -> str:
    """``readme`` with the text between its results markers replaced by ``table``."""
    start, stop = readme.find(BEGIN), readme.find(END)
    if start < 0 or stop < start:
        raise SystemExit(f"{README}: no {BEGIN} ... {END} block to write the table into")
    return readme[: start + len(BEGIN)] + "\n" + table + "\n" + readme[stop:]


def render(matrix: dict, source: Path) -> str:
    rows = matrix["rows"]
    real = [n for n in rows if n.startswith(("tum-", "7scenes"))]
    synthetic = [n for n in rows if n not in real]
    m = matrix.get("machine", {})
    head = [
        "# Results",
        "",
        f"Today's default configuration on every shared sequence and the scene matrix: "
        f"commit `{matrix.get('commit') or _commit()}`, {time.strftime('%Y-%m-%d', time.localtime(source.stat().st_mtime))},"
        f" {m.get('cpus', '?')} CPU cores, {m.get('platform', '?')}, Python "
        f"{m.get('python', '?')}. Written by `python benchmarks/results_page.py --run` from "
        f"`{source.relative_to(ROOT)}`, one run per row (run-to-run spreads: "
        "docs/decisions.md).",
        "",
        "ATE in millimetres (RMSE after SE(3) alignment; odometry / **final**), the worst "
        "frame-to-frame step error of odometry (mm), whole-run fps (the matrix runs rows "
        "one after another on the same machine: compare fps within a page only), the peak "
        "memory of the run's process (MB), the frames colour joined depth in, and the frames "
        "lost. `-x3`: the recording on every third "
        "frame (its motion three times as fast); `-hh`: synthetic rows imitating a hand-held "
        "Kinect v1.",
        "",
    ]
    table = [
        "| sequence | frames | odometry / final ATE (mm) | worst step (mm) | fps | peak MB "
        "| colour frames | lost |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    out = head + ["## Real recordings", ""] + table + [_row(n, rows[n]) for n in real]
    out += ["", "## Synthetic scene matrix", ""] + table + [_row(n, rows[n]) for n in synthetic]
    return "\n".join(out + extra_sections()) + "\n"


def extra_sections() -> list[str]:
    """The localisation, mesh-accuracy, reference-speed and kernel tables, from their own
    benchmarks' latest results (``localisation-*.json``, ``mesh-accuracy-per-view.json``,
    ``alternate-vs-1122-*.json``, ``kernels.json``), when present."""
    out: list[str] = []
    loc = sorted(RESULTS.glob("localisation-*.json"))
    if loc:
        out += [
            "", "## Localisation in a saved map",
            "",
            "`python benchmarks/localisation.py SEQ --split N`: frames before N mapped, the rest "
            "localised in that map (`slam run --map`); ATE in mm; time: localising over mapping "
            "the same frames (median of 3 alternating pairs).",
            "",
            "| sequence | split | localised | map frame ATE | aligned ATE | one run's ATE on "
            "those frames | map run's ATE | time ratio |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]  # fmt: skip
        for path in loc:
            d = json.loads(path.read_text())
            first = d["pairs"][0]["localisation"]
            out.append(
                f"| `{d['sequence']}` | {d['split']} | {first['frames_localised']} of "
                f"{first['frames']} | {_mm(first['ate_rmse_map_frame_m'])} | "
                f"{_mm(first['ate_rmse_m'])} | {_mm(d['full_run_error_on_localised_frames_m'])} | "
                f"{_mm(d['map_run']['ate_rmse_m'])} | "
                f"{d['median_seconds_ratio_localisation_over_mapping']:.2f} |"
            )
    mesh = RESULTS / "mesh-accuracy-per-view.json"
    if mesh.is_file():
        rows = json.loads(mesh.read_text())["rows"]
        out += [
            "", "## Mesh accuracy",
            "",
            "`python benchmarks/mesh_accuracy.py ROWS`: distance of the mesh's vertices to the "
            "true surface of synthetic sequences (mm), the mesh aligned as the trajectory is.",
            "",
            "| sequence | median | 90th percentile |",
            "|---|---:|---:|",
        ]  # fmt: skip
        out += [f"| `{n}` | {r['median_mm']:.2f} | {r['p90_mm']:.2f} |" for n, r in rows.items()]
    out += _reference_speed()
    kern = RESULTS / "kernels.json"
    if kern.is_file():
        d = json.loads(kern.read_text())
        w, h = d["size"]
        out += [
            "", "## Compiled passes against the numpy they replaced",
            "",
            f"`python benchmarks/kernels.py`: the same inputs (two `{d['sequence']}` frames at "
            f"{w}x{h}), alternating in one process, median milliseconds a call.",
            "",
            "| pass | numpy | compiled | ratio |",
            "|---|---:|---:|---:|",
        ]  # fmt: skip
        out += [
            f"| {n} | {r['numpy_ms']:.2f} | {r['compiled_ms']:.2f} | {r['ratio']:.2f} |"
            for n, r in d["rows"].items()
        ]
    return out


def _reference_speed() -> list[str]:
    """Today's code against the code of 2026-11-22 (2c63699, issue 54's reference), from
    ``alternate-vs-1122-*.json`` (``benchmarks/alternate.py SEQ --a-rev 2c63699``)."""
    paths = sorted(RESULTS.glob("alternate-vs-1122-*.json"))
    if not paths:
        return []
    out = [
        "", "## Against the code of 2026-11-22",
        "",
        "`python benchmarks/alternate.py SEQ --a-rev 2c63699 --repeats N [--b-config YAML]`: "
        "alternating fresh runs, old (A) and today's code (B); time ratio B / A (median of "
        "the pairs), final / odometry ATE in mm (range over the runs).",
        "",
        "| sequence | today's config | pairs | time B / A | A: final / odometry | "
        "B: final / odometry |",
        "|---|---|---:|---:|---|---|",
    ]  # fmt: skip

    def ranges(runs: list[dict]) -> str:
        def span(key: str) -> str:
            lo, hi = (1e3 * f(r[key] for r in runs) for f in (min, max))
            return f"{lo:.1f}" if round(lo, 1) == round(hi, 1) else f"{lo:.1f}-{hi:.1f}"

        return f"{span('ate_rmse_m')} / {span('ate_rmse_odometry_m')}"

    for path in paths:
        d = json.loads(path.read_text())
        pairs = d["pairs"]
        config = Path(d["b"]["config"]).stem if d["b"]["config"] else "default"
        out.append(
            f"| `{d['sequence']}` | {config} | {len(pairs)} | "
            f"{d['median_seconds_ratio_b_over_a']:.3f} | {ranges([p['a'] for p in pairs])} | "
            f"{ranges([p['b'] for p in pairs])} |"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="store_true", help="run the scene matrix first")
    ap.add_argument("--matrix", type=Path, default=None, help="a matrix result to write from")
    args = ap.parse_args()
    source = args.matrix
    if args.run:
        subprocess.run(
            [sys.executable, str(ROOT / "benchmarks" / "matrix.py"), "--tag", "results"],
            check=True,
        )
        source = ROOT / "benchmarks" / "results" / "matrix-results.json"
    if source is None:
        ap.error("give --run or --matrix FILE")
    source = source.resolve()
    matrix = json.loads(source.read_text())
    PAGE.write_text(render(matrix, source))
    README.write_text(with_readme_table(README.read_text(), readme_table(matrix)))
    print(f"wrote {PAGE} and the table of {README}")


if __name__ == "__main__":
    main()
