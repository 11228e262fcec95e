"""Where the chunks run: Ray tasks (a local Ray instance, or the cluster at ``ray_address``;
Ray retries a task whose worker died) or, where Ray is not installed, local worker processes
(a pool that is rebuilt, and its unfinished chunks resubmitted, when a worker dies). Every
chunk runs in a fresh process whose kernels use ``threads`` threads."""

from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from slam.chunked.worker import run_chunk, set_kernel_threads
from slam.errors import SlamError
from slam.tools.ray_session import ray_session

log = logging.getLogger(__name__)

#: how many times a chunk whose worker died is run again
RETRIES = 2


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_tasks(
    tasks: list[dict[str, Any]],
    workers: int,
    executor: str = "auto",
    ray_address: str | None = None,
) -> list[dict[str, Any]]:
    """Run every task (:func:`~slam.chunked.worker.run_chunk`), at most ``workers`` at once;
    the reports in the tasks' order. ``executor``: ``ray``, ``processes`` or ``auto`` (Ray
    where it is installed or ``ray_address`` is given, else processes)."""
    if executor == "auto":
        executor = "ray" if ray_address is not None or ray_available() else "processes"
    if executor == "ray":
        return _run_ray(tasks, workers, ray_address)
    if executor == "processes":
        return _run_processes(tasks, workers)
    raise SlamError(f"unknown executor {executor!r}: use 'ray', 'processes' or 'auto'")


def _run_ray(
    tasks: list[dict[str, Any]], workers: int, address: str | None
) -> list[dict[str, Any]]:
    hint = "run without --ray for a local instance"
    with ray_session(address, workers, hint) as ray:
        # a fresh worker process per chunk (its kernel threads are set before Open3D loads);
        # Ray runs a chunk again when its worker dies
        remote = ray.remote(num_cpus=1, max_calls=1, max_retries=RETRIES)(run_chunk)
        try:
            return list(ray.get([remote.remote(t) for t in tasks]))
        except ray.exceptions.RayError as exc:
            raise SlamError(f"a chunk failed on Ray after {RETRIES} retries: {exc}") from exc


def _run_processes(tasks: list[dict[str, Any]], workers: int) -> list[dict[str, Any]]:
    threads = tasks[0]["threads"] if tasks else 1
    reports: dict[int, dict[str, Any]] = {}
    attempts = 0
    while len(reports) < len(tasks):
        todo = [k for k in range(len(tasks)) if k not in reports]
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(
            min(workers, len(todo)), mp_context=ctx, initializer=set_kernel_threads,
            initargs=(threads,),
        ) as pool:  # fmt: skip
            futures: dict[int, Future] = {k: pool.submit(run_chunk, tasks[k]) for k in todo}
            wait(list(futures.values()))
        broken = []
        for k, fut in futures.items():
            try:
                reports[k] = fut.result()
            except BrokenProcessPool as exc:
                broken.append((k, exc))
        if broken:
            attempts += 1
            if attempts > RETRIES:
                raise SlamError(
                    f"chunks {[k for k, _ in broken]}: their worker process died "
                    f"{attempts} times ({broken[0][1]}); see the log"
                )
            log.warning("a worker process died: running chunks %s again", [k for k, _ in broken])
    return [reports[k] for k in range(len(tasks))]
