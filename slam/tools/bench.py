"""Benchmark suites: many sequences x configurations, one results table.

A suite is a YAML file::

    name: quick                 # optional (default: the file name)
    max_frames: 300             # optional, for every sequence (a sequence entry may override it)
    sequences:
      - demo                    # the built-in synthetic demo (slam.demo.demo_sequence_path())
      - ../shared/datasets/7scenes-300             # relative to the suite file's folder
      - {name: cabinet, path: ../shared/datasets/tum-fr3-cabinet-kf58, max_frames: 58}
    configs:                    # optional (default: {default: {}})
      default: {}                               # the defaults of slam.config.SlamConfig
      voxel_2cm: {mapping: {voxel_size_m: 0.02}}  # overrides in the config tree format
      tuned: configs/tuned.yaml                 # or a YAML config file (slam run --config)

:func:`run_suite` runs every (sequence, configuration) pair through the public API
(:func:`slam.api.run_sequence`), each in a fresh process writing its own run folder
``OUT/runs/<sequence>__<config>/``, then evaluates it as ``slam eval RUN_DIR`` does and writes one
table (``bench.md``, ``bench.csv``, ``bench.json`` in ``OUT``) with ATE, RPE, drift, loops, fps and
peak memory per run. Runs go to local processes (``jobs`` at a time) or, with ``ray_address``, to
Ray tasks (``pip install 'rgbd-slam[ray]'``): the same :func:`run_job` either way, so the tables
agree. Paths must be readable where the runs execute (a shared file system on a Ray cluster).

A run that fails (missing sequence, bad configuration key, crash) is a row with ``status`` =
``failed`` and its ``error``; the suite goes on.
"""

from __future__ import annotations

import logging
import multiprocessing
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slam.config import read_yaml
from slam.errors import ConfigError, SlamError
from slam.tools.bench_suite import (
    DEMO,
    Suite,
    SuiteSequence,
    load_suite,
    suite_from_dict,
)
from slam.tools.bench_tables import (
    ACCURACY_COLUMNS,
    COLUMNS,
    format_csv,
    format_markdown,
    write_tables,
)
from slam.tools.ray_session import import_ray, ray_session

logger = logging.getLogger(__name__)

__all__ = [
    "ACCURACY_COLUMNS",
    "COLUMNS",
    "BenchJob",
    "BenchResult",
    "DEMO",
    "Suite",
    "SuiteSequence",
    "load_suite",
    "format_csv",
    "format_markdown",
    "make_jobs",
    "run_job",
    "run_suite",
    "suite_from_dict",
    "write_tables",
]

# ----------------------------------------------------------------------------------------------
# jobs


@dataclass
class BenchJob:
    """One run of a suite; plain data, so it pickles to a process or a Ray worker. ``error`` set
    means the job failed before it could start (bad configuration)."""

    index: int
    sequence: str
    config: str
    sequence_path: str
    config_overrides: dict[str, Any]
    max_frames: int | None
    run_dir: str
    error: str | None = None


def _resolve(base: Path, p: str) -> str:
    q = Path(p).expanduser()
    return str(q if q.is_absolute() else (base / q).resolve())


def _config_dict(suite: Suite, cfg: dict[str, Any] | str) -> dict[str, Any]:
    from slam.config import config_from_dict

    if isinstance(cfg, str):
        path = Path(_resolve(suite.base_dir, cfg))
        data = read_yaml(path) or {}
        where = f"{path}: "
    else:
        data, where = cfg, ""
    try:
        config_from_dict(data)  # validate here: a bad key fails fast, without a process
    except ConfigError as exc:
        raise ConfigError(f"{where}{exc}") from exc
    return data


def make_jobs(suite: Suite, out_dir: str | Path) -> list[BenchJob]:
    """Every (sequence, configuration) pair of the suite, sequences first, in suite order.
    ``demo`` is resolved (and generated on first use) here, once."""
    out = Path(out_dir)
    jobs: list[BenchJob] = []
    demo_path: str | None = None
    for seq in suite.sequences:
        if seq.path == DEMO:
            if demo_path is None:
                from slam.demo import demo_sequence_path

                demo_path = str(demo_sequence_path())
            seq_path = demo_path
        else:
            seq_path = _resolve(suite.base_dir, seq.path)
        for cname, cfg in suite.configs.items():
            error = None
            overrides: dict[str, Any] = {}
            try:
                overrides = _config_dict(suite, cfg)
            except ConfigError as exc:
                error = f"ConfigError: {exc}"
            jobs.append(
                BenchJob(
                    index=len(jobs),
                    sequence=seq.name,
                    config=cname,
                    sequence_path=seq_path,
                    config_overrides=overrides,
                    max_frames=seq.max_frames if seq.max_frames is not None else suite.max_frames,
                    run_dir=str(out / "runs" / f"{seq.name}__{cname}"),
                    error=error,
                )
            )
    return jobs


def _row(job: BenchJob, status: str, error: str | None = None) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(COLUMNS)
    row.update(sequence=job.sequence, config=job.config, status=status, run_dir=job.run_dir)
    row["error"] = error
    return row


def _failed(job: BenchJob, error: str) -> dict[str, Any]:
    logger.debug("%s / %s failed: %s", job.sequence, job.config, error)
    return _row(job, "failed", error)


def run_job(job: BenchJob) -> dict[str, Any]:
    """Run one job (in the calling process) and return its table row; never raises for a failed
    run. Writes the run folder plus ``log.txt`` (this run's log records) into ``job.run_dir``."""
    if job.error is not None:
        return _failed(job, job.error)
    from slam.api import run_sequence
    from slam.config import config_from_dict
    from slam.tools.eval import evaluate_run

    run_dir = Path(job.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(run_dir / "log.txt", mode="w")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    if old_level > logging.INFO:
        root.setLevel(logging.INFO)
    try:
        cfg = config_from_dict(job.config_overrides)
        t0 = time.perf_counter()
        result, _ = run_sequence(job.sequence_path, run_dir, config=cfg, max_frames=job.max_frames)
        m = result.metrics
        row = _row(job, "ok")
        row.update(
            frames=m.get("frames"),
            loops_accepted=m.get("loops_accepted"),
            tracking_failures=m.get("tracking_failures"),
            fps=m.get("fps"),
            seconds=m.get("seconds", round(time.perf_counter() - t0, 3)),
            peak_rss_mb=m.get("peak_rss_mb"),
        )
        try:
            ev = evaluate_run(run_dir)  # exactly what `slam eval RUN_DIR` reports
        except SlamError as exc:
            row["error"] = f"not evaluated: {exc}"
        else:
            head = ev.final.headline()
            row.update(
                ate_rmse_m=head["ate_rmse_m"],
                rpe_trans_rmse_m=head["rpe_trans_rmse_m"],
                rpe_rot_rmse_deg=head["rpe_rot_rmse_deg"],
                drift_percent=head["drift_percent"],
                ate_rmse_odometry_m=ev.odometry.ate.rmse if ev.odometry is not None else None,
            )
        return row
    except SlamError as exc:
        logger.error("run failed: %s: %s", type(exc).__name__, exc)
        return _failed(job, f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # a crash in one run must not stop the suite
        logger.error("%s / %s crashed:\n%s", job.sequence, job.config, traceback.format_exc())
        return _failed(job, f"{type(exc).__name__}: {exc} (traceback in {run_dir / 'log.txt'})")
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        handler.close()


# ----------------------------------------------------------------------------------------------
# executors


RowCallback = Callable[[dict[str, Any], int, int], None]


def _run_local(
    jobs: list[BenchJob], workers: int, on_row: Callable[[BenchJob, dict[str, Any]], None]
) -> None:
    ctx = multiprocessing.get_context("spawn")
    kw: dict[str, Any] = {}
    if sys.version_info >= (3, 11):
        kw["max_tasks_per_child"] = 1  # fresh process per run: clean state, true peak memory
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, **kw) as pool:
        futures = {pool.submit(run_job, job): job for job in jobs}
        for fut in as_completed(futures):
            job = futures[fut]
            try:
                row = fut.result()
            except Exception as exc:  # the worker process died (segfault, out of memory, ...)
                row = _failed(job, f"worker process failed: {type(exc).__name__}: {exc}")
            on_row(job, row)


def _run_ray(
    jobs: list[BenchJob],
    address: str,
    workers: int,
    on_row: Callable[[BenchJob, dict[str, Any]], None],
) -> None:
    local = None if address == "local" else address
    with ray_session(local, workers, "use --ray local for a one-off local instance") as ray:
        task = ray.remote(num_cpus=1, max_calls=1)(run_job)  # fresh worker process per run
        refs = {task.remote(job): job for job in jobs}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                job = refs[ref]
                try:
                    row = ray.get(ref)
                except Exception as exc:  # the task's worker died
                    row = _failed(job, f"Ray task failed: {type(exc).__name__}: {exc}")
                on_row(job, row)


@dataclass
class BenchResult:
    rows: list[dict[str, Any]]
    tables: dict[str, Path]

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if r["status"] != "ok"]


def _warn_missing_sequences(suite: Suite) -> None:
    """Say before any run which sequence folders are missing (their runs will fail as rows)."""
    missing = [
        seq.path for seq in suite.sequences
        if seq.path != DEMO and not Path(_resolve(suite.base_dir, seq.path)).is_dir()
    ]  # fmt: skip
    if missing:
        runs = len(missing) * len(suite.configs)
        logger.warning(
            "suite %s: %d sequence folder(s) not found, so %d run(s) will fail: %s (relative "
            "paths are relative to the suite file's folder, %s)",
            suite.name, len(missing), runs, ", ".join(missing), suite.base_dir,
        )  # fmt: skip


def run_suite(
    suite: Suite | str | Path,
    out_dir: str | Path,
    jobs: int = 1,
    ray_address: str | None = None,
    progress: RowCallback | None = None,
) -> BenchResult:
    """Run a suite (a :class:`Suite` or a YAML path) and write its tables into ``out_dir``.

    ``jobs``: local processes at a time (and the CPUs of a ``local`` Ray instance).
    ``ray_address``: ``None`` for local processes; else Ray tasks on the cluster at that address
    (``auto``: the running cluster, ``ray://host:10001``: a remote one, ``local``: start a
    private local instance); an already initialised Ray (``ray.init`` called by the caller) is
    used as it is. ``progress(row, done, total)`` is called as each run finishes.
    Rows come back in suite order, whatever the completion order.
    """
    if not isinstance(suite, Suite):
        suite = load_suite(suite)
    if jobs < 1:
        raise ConfigError(f"jobs must be >= 1, got {jobs}")
    if ray_address is not None:
        import_ray()  # fail before any work when Ray is missing
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _warn_missing_sequences(suite)
    all_jobs = make_jobs(suite, out)
    rows: list[dict[str, Any] | None] = [None] * len(all_jobs)
    done = [0]

    def on_row(job: BenchJob, row: dict[str, Any]) -> None:
        rows[job.index] = row
        done[0] += 1
        logger.debug(
            "[%d/%d] %s / %s: %s",
            done[0],
            len(all_jobs),
            job.sequence,
            job.config,
            row["status"] if row["status"] == "ok" else f"failed: {row['error']}",
        )
        if progress is not None:
            progress(row, done[0], len(all_jobs))

    runnable = []
    for job in all_jobs:
        if job.error is not None:
            on_row(job, _failed(job, job.error))
        else:
            runnable.append(job)
    t0 = time.perf_counter()
    if runnable:
        if ray_address is None:
            _run_local(runnable, min(jobs, len(runnable)), on_row)
        else:
            _run_ray(runnable, ray_address, jobs, on_row)
    final = [r for r in rows if r is not None]
    tables = write_tables(
        final,
        out,
        suite.name,
        {
            "executor": "local" if ray_address is None else f"ray:{ray_address}",
            "jobs": jobs,
            "wall_seconds": round(time.perf_counter() - t0, 3),
        },
    )
    return BenchResult(final, tables)
