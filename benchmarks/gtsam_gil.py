"""Does GTSAM's optimiser release Python's GIL? (Whether the backend could run beside tracking
in a thread of the same process.)

    python benchmarks/gtsam_gil.py

Optimises a pose graph of 3,000 poses (odometry chain plus loop edges) with
Levenberg-Marquardt, 10 times, while a second thread counts in a pure-Python loop. A call
that releases the GIL leaves the counting thread at its full rate on the other core; one that
holds it stops the thread for as long as it runs. Writes ``benchmarks/results/gtsam-gil.json`` with
the counting rates before and during the optimisation.
"""

from __future__ import annotations

import threading
import time

import gtsam
import numpy as np
from common import machine, write_result

POSES = 3000
REPEATS = 10


def pose_graph() -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 0.1))
    step, loop = np.array([0.1, 0.0, 0.0]), np.array([5.0, 0.0, 0.0])
    for i in range(POSES):
        values.insert(i, gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * i + 0.01 * np.sin(i), 0, 0])))
        if i:
            graph.add(gtsam.BetweenFactorPose3(i - 1, i, gtsam.Pose3(gtsam.Rot3(), step), noise))
        if i > 50 and i % 7 == 0:
            graph.add(gtsam.BetweenFactorPose3(i - 50, i, gtsam.Pose3(gtsam.Rot3(), loop), noise))
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), noise))
    return graph, values


def main() -> None:
    graph, values = pose_graph()
    state = {"count": 0, "done": False}

    def count() -> None:
        while not state["done"]:
            state["count"] += 1

    thread = threading.Thread(target=count)
    thread.start()
    time.sleep(0.2)
    c0, t0 = state["count"], time.perf_counter()
    time.sleep(0.5)
    before = (state["count"] - c0) / (time.perf_counter() - t0)
    c1, t1 = state["count"], time.perf_counter()
    for _ in range(REPEATS):  # long enough a window to count in
        gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    seconds = time.perf_counter() - t1
    during = (state["count"] - c1) / seconds
    state["done"] = True
    thread.join()
    out = {
        "poses": POSES,
        "optimisations": REPEATS,
        "optimize_s": round(seconds, 3),
        "python_thread_rate_before": round(before),
        "python_thread_rate_during": round(during),
        "share_during": round(during / before, 3),
        "machine": machine(),
    }
    path = write_result("gtsam-gil", out)
    print(f"{path}: the Python thread ran at {out['share_during']:.0%} of its rate during "
          f"{seconds:.2f} s of optimisation")  # fmt: skip


if __name__ == "__main__":
    main()
