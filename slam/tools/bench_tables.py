"""The results table of a benchmark suite (:mod:`slam.tools.bench`): one row per run, as
Markdown, CSV and JSON."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from slam.trajectory import atomic_write_text

__all__ = ["ACCURACY_COLUMNS", "COLUMNS", "format_csv", "format_markdown", "write_tables"]

#: Columns of the results table, in order.
COLUMNS = (
    "sequence",
    "config",
    "status",
    "frames",
    "ate_rmse_m",
    "ate_rmse_odometry_m",
    "rpe_trans_rmse_m",
    "rpe_rot_rmse_deg",
    "drift_percent",
    "loops_accepted",
    "tracking_failures",
    "fps",
    "seconds",
    "peak_rss_mb",
    "run_dir",
    "error",
)

#: Columns that depend only on the input and the code, not on the machine's load (a local and a
#: Ray run of the same suite must agree on them).
ACCURACY_COLUMNS = (
    "frames",
    "ate_rmse_m",
    "ate_rmse_odometry_m",
    "rpe_trans_rmse_m",
    "rpe_rot_rmse_deg",
    "drift_percent",
    "loops_accepted",
    "tracking_failures",
)

_MD_FORMATS = {
    "ate_rmse_m": ".4f",
    "ate_rmse_odometry_m": ".4f",
    "rpe_trans_rmse_m": ".4f",
    "rpe_rot_rmse_deg": ".3f",
    "drift_percent": ".2f",
    "fps": ".1f",
    "seconds": ".1f",
    "peak_rss_mb": ".0f",
}


def _md_cell(col: str, v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        return format(v, _MD_FORMATS.get(col, ".4g"))
    text = str(v).replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= 160 else text[:157] + "..."


def format_markdown(rows: list[dict[str, Any]], title: str = "") -> str:
    """The results table as Markdown (``-`` for no value)."""
    cols = [c for c in COLUMNS if c != "run_dir"]
    lines = [f"# Benchmark: {title}", ""] if title else []
    ok = sum(r["status"] == "ok" for r in rows)
    lines += [
        f"{len(rows)} runs, {ok} ok, {len(rows) - ok} failed. ATE/RPE as `evo_ape`/`evo_rpe -a` "
        "(SE(3)-aligned, RPE over 1 frame); drift: final position error after that alignment in "
        "% of the ground-truth path length; peak memory: the run process's maximum RSS.",
        "",
        "| " + " | ".join(cols) + " |",
        "|"
        + "|".join("---:" if c in _MD_FORMATS or c in ACCURACY_COLUMNS else "---" for c in cols)
        + "|",
    ]
    for r in rows:
        lines.append("| " + " | ".join(_md_cell(c, r.get(c)) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def format_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(COLUMNS), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    return buf.getvalue()


def _json_value(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def write_tables(
    rows: list[dict[str, Any]], out_dir: str | Path, title: str = "", extra: dict | None = None
) -> dict[str, Path]:
    """Write ``bench.md``, ``bench.csv`` and ``bench.json`` (atomically) into ``out_dir``."""
    out = Path(out_dir)
    paths = {"md": out / "bench.md", "csv": out / "bench.csv", "json": out / "bench.json"}
    atomic_write_text(paths["md"], format_markdown(rows, title))
    atomic_write_text(paths["csv"], format_csv(rows))
    doc = {
        "suite": title,
        **(extra or {}),
        "columns": list(COLUMNS),
        "rows": [{k: _json_value(r.get(k)) for k in COLUMNS} for r in rows],
    }
    atomic_write_text(paths["json"], json.dumps(doc, indent=2) + "\n")
    return paths
