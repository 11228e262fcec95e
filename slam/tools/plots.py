"""The project's matplotlib figures (Agg backend, no display), written atomically as PNG:
trajectories in the plane they extend most in (:func:`plot_trajectories`, used by
``slam eval --plot`` and ``slam report``, which therefore draw one run in the same plane:
:func:`trajectory_plane`), and the report's error-over-time and timing plots."""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import TrajectoryError
from slam.trajectory import Trajectory

logger = logging.getLogger(__name__)

__all__ = [
    "PlotPlane",
    "ground_truth_during",
    "plot_error",
    "plot_plane",
    "plot_timing",
    "plot_trajectories",
    "save_figure",
    "trajectory_plane",
]


_AXIS_NAMES = "xyz"
#: A principal direction this close to a coordinate axis is drawn as that axis (degrees).
_SNAP_DEG = 20.0


@dataclass
class PlotPlane:
    """The plane a trajectory plot shows: unit directions ``u`` (horizontal) and ``v``
    (vertical) in world coordinates, their axis labels, and the plane's name (``"x-y plane"``
    when both are coordinate axes, else ``"plane of largest extent"``)."""

    u: np.ndarray
    v: np.ndarray
    u_label: str
    v_label: str
    name: str

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(points, float).reshape(-1, 3)
        return p @ self.u, p @ self.v


def _direction_label(d: np.ndarray) -> str:
    k = int(np.argmax(np.abs(d)))
    if np.isclose(abs(d[k]), 1.0):
        return _AXIS_NAMES[k]
    terms = [(c, _AXIS_NAMES[i]) for i, c in enumerate(d) if abs(c) >= 0.005]
    out = f"{terms[0][0]:.2f} {terms[0][1]}"
    for c, n in terms[1:]:
        out += f" {'-' if c < 0 else '+'} {abs(c):.2f} {n}"
    return out


def _snap(d: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(d)))
    if abs(d[k]) >= np.cos(np.radians(_SNAP_DEG)):
        e = np.zeros(3)
        e[k] = 1.0
        return e
    return d * np.sign(d[k])  # the largest component positive


def plot_plane(points: np.ndarray) -> PlotPlane:
    """The plane in which ``points`` extend most: their two principal directions (PCA), each
    drawn as the nearest coordinate axis when within 20 degrees of it (so a trajectory that
    moves in a floor or table plane is shown in that plane, and a plot names x, y, z where it
    can). Points with no spread give the x-z plane (the floor of a y-down camera)."""
    x, z = np.eye(3)[0], np.eye(3)[2]
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 2 or not np.any(np.ptp(p, axis=0) > 1e-12):
        return PlotPlane(x, z, "x", "z", "x-z plane")
    c = p - p.mean(0)
    w, vecs = np.linalg.eigh(c.T @ c)
    e1 = _snap(vecs[:, 2])
    e2 = vecs[:, 1] - (vecs[:, 1] @ e1) * e1
    if np.linalg.norm(e2) < 1e-9 or w[1] <= 1e-12 * max(w[2], 1e-300):
        # a line: the second direction is free; take the coordinate axis most across it
        k = int(np.argmin(np.abs(e1) + np.array([0.0, 1e-6, 0.0])))  # prefer x, z over y
        e2 = np.eye(3)[k] - (np.eye(3)[k] @ e1) * e1
    e2 = _snap(e2 / np.linalg.norm(e2))
    if np.count_nonzero(e1) == 1 and np.count_nonzero(e2) == 1:
        a, b = sorted((int(np.argmax(e1)), int(np.argmax(e2))))
        e1, e2 = np.eye(3)[a], np.eye(3)[b]
        name = f"{_AXIS_NAMES[a]}-{_AXIS_NAMES[b]} plane"
    else:
        name = "plane of largest extent"
    return PlotPlane(e1, e2, _direction_label(e1), _direction_label(e2), name)


def ground_truth_during(
    gt: Trajectory, trajectories: Sequence[Trajectory], tol: float = 0.01
) -> Trajectory:
    """The part of the ground truth over the time the trajectories cover (first to last
    timestamp, ``tol`` s either side): a run of part of a sequence, or motion capture that
    starts before the camera, would otherwise draw (and choose its plane from) what was not
    run. The whole ground truth when fewer than 2 of its poses fall in that time."""
    spans = [(t.timestamps[0], t.timestamps[-1]) for t in trajectories if len(t)]
    if not spans or len(gt) == 0:
        return gt
    t0, t1 = min(a for a, _ in spans), max(b for _, b in spans)
    t = gt.timestamps
    keep = (t >= t0 - tol) & (t <= t1 + tol)
    return Trajectory(t[keep], gt.poses[keep]) if np.count_nonzero(keep) >= 2 else gt


def trajectory_plane(
    gt: Trajectory | None, trajectories: dict[str, Trajectory], tol: float = 0.01
) -> PlotPlane:
    """The plane :func:`plot_trajectories` draws in: :func:`plot_plane` of the ground truth
    during the trajectories (:func:`ground_truth_during`), or without ground truth of all the
    trajectories' positions. ``slam eval --plot`` and ``slam report`` both draw through it, so
    they show one run in the same plane."""
    trajs = [t for t in trajectories.values() if len(t)]
    if gt is not None and len(gt):
        return plot_plane(ground_truth_during(gt, trajs, tol).positions)
    return plot_plane(np.concatenate([t.positions for t in trajs] or [np.zeros((0, 3))]))


def save_figure(fig: Any, path_png: str | Path) -> Path:
    """Save a matplotlib ``Figure`` as PNG atomically (temporary file, then rename)."""
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            fig.savefig(f, format="png")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def plot_trajectories(
    path_png: str | Path,
    gt: Trajectory | None,
    trajectories: dict[str, Trajectory],
    title: str = "",
    loop_edges: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    loop_label: str = "loop edge",
    tol: float = 0.01,
) -> PlotPlane:
    """Plot of the ground truth and any number of trajectories, saved as a PNG; returns the
    plane shown.

    The ground truth is drawn over the time the trajectories cover (:func:`ground_truth_during`,
    ``tol`` s either side). The plane is the one in which that ground truth (or, without one,
    all trajectories) extends most (:func:`trajectory_plane`); the axis labels say which
    directions it spans. Trajectories are
    plotted as given (use :func:`align_trajectory` first to overlay an estimate on the ground
    truth). ``loop_edges`` are pairs of 3D positions joined by a thin, light line (e.g. the two
    camera positions of an accepted loop closure; the more there are, the lighter), all under
    one legend entry ``loop_label``. Written atomically.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    trajectories = dict(trajectories or {})
    if gt is None and not trajectories:
        raise TrajectoryError(
            "plot_trajectories: nothing to plot (no ground truth, no trajectories)"
        )
    if gt is not None and len(gt):
        gt = ground_truth_during(gt, [t for t in trajectories.values() if len(t)], tol)
    plane = trajectory_plane(gt, trajectories, tol)

    fig = Figure(figsize=(8, 7), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None and len(gt):
        pu, pv = plane.project(gt.positions)
        ax.plot(pu, pv, color="black", linestyle="--", linewidth=1.5, label="ground truth")
        ax.plot(pu[0], pv[0], marker="o", color="black", markersize=5, linestyle="none")
    for name, traj in trajectories.items():
        if len(traj) == 0:
            logger.warning("plot_trajectories: trajectory %r is empty, skipped", name)
            continue
        pu, pv = plane.project(traj.positions)
        (line,) = ax.plot(pu, pv, linewidth=1.2, label=str(name))
        ax.plot(pu[0], pv[0], marker="o", color=line.get_color(), markersize=4, linestyle="none")
    if len(loop_edges):
        a = np.array([np.asarray(p0, float) for p0, _ in loop_edges])
        b = np.array([np.asarray(p1, float) for _, p1 in loop_edges])
        au, av = plane.project(a)
        bu, bv = plane.project(b)
        segs = np.stack([np.stack([au, av], 1), np.stack([bu, bv], 1)], 1)
        alpha = float(np.clip(3.0 / np.sqrt(len(segs)), 0.12, 0.7))
        ax.add_collection(LineCollection(segs, colors="red", linewidths=0.6, alpha=alpha, zorder=3))
        ax.plot(
            np.r_[au, bu], np.r_[av, bv], ".", color="red", markersize=2.5, alpha=alpha, zorder=3
        )
        # an empty line carries the legend entry of the collection
        proxy = Line2D([], [], color="red", linewidth=0.8, alpha=max(alpha, 0.5))
        proxy.set_label(f"{loop_label} ({len(segs)})")
        ax.add_line(proxy)
    ax.set_xlabel(f"{plane.u_label} [m]")
    ax.set_ylabel(f"{plane.v_label} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = save_figure(fig, path_png)
    logger.debug("wrote trajectory plot %s (%s)", path, plane.name)
    return plane


def _figure(figsize: tuple[float, float]) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


def plot_error(
    path: Path,
    curves: dict[str, tuple[np.ndarray, np.ndarray]],
    t0: float,
    loop_times: list[float],
    title: str,
) -> Path:
    fig = _figure((9, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    # same colours as the trajectory plot (matplotlib's cycle: odometry first when shown)
    colors = {"odometry": "C0", "final": "C1"} if "odometry" in curves else {"final": "C0"}
    for name, (t, err) in curves.items():
        rmse = float(np.sqrt(np.mean(err**2)))
        ax.plot(
            t - t0,
            err,
            linewidth=1.1,
            color=colors.get(name),
            label=f"{name} (ATE rmse {rmse:.3f} m)",
        )
    for k, t_loop in enumerate(sorted(loop_times)):
        ax.axvline(
            t_loop - t0,
            color="red",
            linewidth=0.6,
            alpha=0.35,
            label=f"accepted loop closure ({len(loop_times)})" if k == 0 else None,
        )
    ax.set_xlabel("time since the first frame [s]")
    ax.set_ylabel("translation error after alignment [m]")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left")
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_timing(
    path: Path,
    stages: list[tuple[str, float]],
    wall_s: float,
    tracking: dict[str, np.ndarray] | None,
    title: str,
) -> Path | None:
    ms = None if tracking is None else tracking.get("ms")
    has_ms = ms is not None and ms.dtype.kind == "f" and len(ms) > 0
    if not stages and not has_ms:
        return None
    n = int(bool(stages)) + int(has_ms)
    fig = _figure((6.0 * n, 4.5))
    k = 1
    if stages:
        ax = fig.add_subplot(1, n, k)
        k += 1
        names = [s for s, _ in stages][::-1]
        secs = np.array([v for _, v in stages][::-1]) / 1e3
        bars = ax.barh(names, secs, color="tab:gray")
        for bar, v in zip(bars, secs):
            ax.text(
                bar.get_width(),
                bar.get_y() + bar.get_height() / 2,
                f" {v:.1f} s ({100 * v / wall_s:.0f} %)" if wall_s > 0 else f" {v:.1f} s",
                va="center",
                fontsize=8,
            )
        ax.set_xlabel("total time [s] (% of the run's wall time)")
        ax.set_xlim(0, max(float(secs.max()) * 1.35, 1e-3))
        ax.set_title("time per stage")
        ax.grid(True, axis="x", alpha=0.3)
    if has_ms:
        assert tracking is not None and ms is not None
        ax = fig.add_subplot(1, n, k)
        idx = tracking.get("index")
        x = idx if idx is not None and idx.dtype.kind == "f" else np.arange(len(ms))
        ax.plot(x, ms, linewidth=0.7, color="C0", label="tracking time per frame")
        if len(ms) >= 15:
            w = 15
            smooth = np.convolve(ms, np.ones(w) / w, mode="valid")
            ax.plot(x[w // 2 : w // 2 + len(smooth)], smooth, color="black", linewidth=1.2,
                    label=f"moving mean ({w} frames)")  # fmt: skip
        kf = tracking.get("keyframe")
        if kf is not None and kf.dtype.kind == "f" and np.any(kf > 0):
            sel = kf > 0
            ax.plot(x[sel], ms[sel], "o", markersize=3, color="tab:green", label="keyframe")
        ok = tracking.get("ok")
        if ok is not None and ok.dtype.kind == "f" and np.any(ok == 0):
            sel = ok == 0
            ax.plot(x[sel], ms[sel], "x", markersize=6, color="red", label="tracking lost")
        ax.set_xlabel("frame")
        ax.set_ylabel("tracking time [ms]")
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
        ax.set_title(f"tracking time per frame (median {np.nanmedian(ms):.0f} ms)")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)
