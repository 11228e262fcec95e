"""How `slam eval` prints its results (plain text; `--json` prints the library's dicts)."""

from __future__ import annotations

import typer

from slam.run_folder import ODOMETRY_FILE

_STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")


def _fmt_stats(stats, unit: str, digits: int = 4) -> str:
    if stats is None:
        return "n/a"
    return (
        f"rmse {stats.rmse:.{digits}f}  mean {stats.mean:.{digits}f}  median "
        f"{stats.median:.{digits}f}  std {stats.std:.{digits}f}  min {stats.min:.{digits}f}  "
        f"max {stats.max:.{digits}f} {unit}"
    )


def echo_result(res) -> None:
    typer.echo(f"matched poses      {res.matched_poses} (alignment {res.alignment})")
    typer.echo(f"ATE                {_fmt_stats(res.ate, 'm')}")
    for r in res.rpe:
        if r.left_out:
            typer.echo(f"RPE {r.label:<14} n/a: {r.left_out}")
            continue
        typer.echo(f"RPE {r.label:<14} trans {_fmt_stats(r.trans, 'm')}  ({r.pairs} pairs)")
        typer.echo(f"{'':18} rot   {_fmt_stats(r.rot, 'deg', 3)}")
    d = res.drift
    typer.echo(
        f"drift              {d.percent:.3f} % ({d.final_error_m:.4f} m final error over "
        f"{d.path_length_m:.2f} m, {d.alignment} alignment)"
    )


def echo_run(ev) -> None:
    """Final vs odometry side by side."""
    rows: list[tuple[str, str, str]] = []

    def val(res, get, fmt):
        if res is None:
            return "-"
        v = get(res)
        return "n/a" if v is None else format(v, fmt)

    fin, odo = ev.final, ev.odometry
    rows.append(
        (
            "matched poses",
            val(fin, lambda r: r.matched_poses, "d"),
            val(odo, lambda r: r.matched_poses, "d"),
        )
    )
    for k in _STAT_KEYS:
        rows.append(
            (
                f"ATE {k} [m]",
                val(fin, lambda r, k=k: getattr(r.ate, k), ".4f"),
                val(odo, lambda r, k=k: getattr(r.ate, k), ".4f"),
            )
        )
    for i, r in enumerate(fin.rpe):

        def t(res, i=i):
            x = res.rpe[i]
            return None if x.left_out or x.trans is None else x.trans.rmse

        def rot(res, i=i):
            x = res.rpe[i]
            return None if x.left_out or x.rot is None else x.rot.rmse

        def pairs(res, i=i):
            return res.rpe[i].pairs

        rows.append((f"RPE {r.label} trans rmse [m]", val(fin, t, ".4f"), val(odo, t, ".4f")))
        rows.append((f"RPE {r.label} rot rmse [deg]", val(fin, rot, ".3f"), val(odo, rot, ".3f")))
        rows.append((f"RPE {r.label} pose pairs", val(fin, pairs, "d"), val(odo, pairs, "d")))
    rows.append(
        (
            "drift [%]",
            val(fin, lambda r: r.drift.percent, ".3f"),
            val(odo, lambda r: r.drift.percent, ".3f"),
        )
    )
    rows.append(
        (
            "final position error [m]",
            val(fin, lambda r: r.drift.final_error_m, ".4f"),
            val(odo, lambda r: r.drift.final_error_m, ".4f"),
        )
    )
    typer.echo(f"run          {ev.run_dir}")
    typer.echo(f"ground truth {ev.ground_truth}")
    if ev.loops_accepted is not None:
        typer.echo(f"loops        {ev.loops_accepted} accepted")
    if ev.odometry is None:
        typer.echo(f"odometry     (no {ODOMETRY_FILE})")
    elif ev.odometry_identical:
        typer.echo("odometry     identical to the final trajectory (no pose corrected)")
    width = max(len(r[0]) for r in rows)
    typer.echo(f"{'':{width}}  {'final':>10}  {'odometry':>10}")
    for name, a, b in rows:
        typer.echo(f"{name:{width}}  {a:>10}  {b:>10}")
    for note in rpe_notes(ev):
        typer.echo(note)


def rpe_notes(ev) -> list[str]:
    """Why an RPE row of a run's evaluation is n/a (too few pose pairs, none), one line each."""
    why: dict[tuple[str, str], list[str]] = {}  # (label, reason) -> the columns
    for name, res in (("final", ev.final), ("odometry", ev.odometry)):
        if res is None or (name == "odometry" and res is ev.final):
            continue
        for r in res.rpe:
            if r.left_out:
                why.setdefault((r.label, r.left_out), []).append(name)
    return [
        f"RPE {label} n/a ({', '.join(names)}): {reason}" for (label, reason), names in why.items()
    ]
