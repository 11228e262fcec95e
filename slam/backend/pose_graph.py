"""Keyframe pose graph on GTSAM: ``Pose3`` nodes, ``BetweenFactorPose3`` odometry and loop edges
(loop edges with a robust noise model), a prior on the first node, Levenberg-Marquardt.

The graph keeps its own plain record of nodes and edges (numpy), so it can be saved, restored
and exported (g2o) independently of GTSAM objects; the GTSAM factor graph is built on demand.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from slam.config import BackendConfig
from slam.errors import ConfigError
from slam.geometry import pose_to_tum
from slam.trajectory import atomic_write_text

log = logging.getLogger(__name__)

#: GTSAM's Pose3 tangent is (rotation, translation); g2o's EDGE_SE3:QUAT is (translation, rotation)
_G2O_ORDER = [3, 4, 5, 0, 1, 2]


@dataclass
class Edge:
    """A relative-pose measurement ``T_i_j`` (node j in node i's frame) with its 6x6 information
    (rotation first, right perturbation of ``T_i_j``). ``kind``: ``odometry`` or ``loop``."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    kind: str
    tag: int = -1  # caller's reference (the loop record's index)


@dataclass
class OptimizationReport:
    iterations: int
    error_before: float
    error_after: float
    ms: float


class PoseGraph:
    """Nodes are keyframe ids with ``T_world_node`` estimates; edges are :class:`Edge`."""

    def __init__(self, cfg: BackendConfig) -> None:
        if cfg.loop_kernel not in ("cauchy", "huber", "none"):
            raise ConfigError(
                f"backend.loop_kernel must be cauchy, huber or none, got {cfg.loop_kernel!r}"
            )
        self.cfg = cfg
        self.nodes: dict[int, np.ndarray] = {}
        self.edges: list[Edge] = []
        # nodes held by a prior: the first node, and the first node of each map segment not yet
        # joined to the others (each connected component needs one to fix its gauge)
        self.anchors: set[int] = set()

    # --- building
    def add_node(self, key: int, T_world_node: np.ndarray) -> None:
        self.nodes[key] = np.asarray(T_world_node, float).copy()

    def add_edge(self, edge: Edge) -> None:
        if edge.i not in self.nodes or edge.j not in self.nodes:
            raise KeyError(f"edge {edge.i}-{edge.j}: both nodes must be added first")
        info = 0.5 * (edge.information + edge.information.T)
        if np.linalg.eigvalsh(info).min() <= 0:
            info = info + np.eye(6) * 1e-9 * max(np.trace(info), 1.0)
        self.edges.append(Edge(edge.i, edge.j, edge.T_i_j.copy(), info, edge.kind, edge.tag))

    @property
    def n_loops(self) -> int:
        return sum(e.kind == "loop" for e in self.edges)

    # --- GTSAM
    def _noise(self, edge: Edge) -> gtsam.noiseModel.Base:
        gaussian = gtsam.noiseModel.Gaussian.Information(edge.information)
        if edge.kind != "loop" or self.cfg.loop_kernel == "none":
            return gaussian
        k = self.cfg.loop_kernel_width
        est = (
            gtsam.noiseModel.mEstimator.Cauchy.Create(k)
            if self.cfg.loop_kernel == "cauchy"
            else gtsam.noiseModel.mEstimator.Huber.Create(k)
        )
        return gtsam.noiseModel.Robust.Create(est, gaussian)

    def _factor_graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for key, T in self.nodes.items():
            values.insert(key, gtsam.Pose3(T))
        for key in self.anchors or {min(self.nodes)}:
            graph.add(
                gtsam.PriorFactorPose3(
                    key, gtsam.Pose3(self.nodes[key]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
                )
            )
        for e in self.edges:
            graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), self._noise(e)))
        return graph, values

    def optimize(self) -> OptimizationReport:
        """Levenberg-Marquardt from the current estimates; updates ``nodes`` in place."""
        t0 = time.perf_counter()
        if len(self.nodes) < 2:
            return OptimizationReport(0, 0.0, 0.0, 0.0)
        graph, values = self._factor_graph()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.max_iterations)
        params.setRelativeErrorTol(1e-6)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        before = graph.error(values)
        result = opt.optimize()
        after = graph.error(result)
        for key in self.nodes:
            self.nodes[key] = result.atPose3(key).matrix()
        report = OptimizationReport(
            opt.iterations(), before, after, (time.perf_counter() - t0) * 1e3
        )
        log.debug(
            "pose graph: %d nodes, %d edges (%d loops): error %.3g -> %.3g in %d iterations, %.1f ms",
            len(self.nodes),
            len(self.edges),
            self.n_loops,
            before,
            after,
            report.iterations,
            report.ms,
        )
        return report

    def whitened_residual(self, edge: Edge) -> float:
        """sqrt(e^T Lambda e) of an edge at the current estimates (Gaussian part, no kernel):
        about 1 for an edge that agrees with the graph to one standard deviation."""
        T_pred = np.linalg.inv(self.nodes[edge.i]) @ self.nodes[edge.j]
        e = gtsam.Pose3.Logmap(gtsam.Pose3(edge.T_i_j).between(gtsam.Pose3(T_pred)))
        return float(np.sqrt(max(e @ edge.information @ e, 0.0)))

    def remove_edge(self, edge: Edge) -> None:
        self.edges = [e for e in self.edges if e is not edge]

    # --- persistence
    def state_dict(self) -> dict:
        return {
            "anchors": sorted(self.anchors),
            "nodes": {k: v.tolist() for k, v in self.nodes.items()},
            "edges": [
                {
                    "i": e.i,
                    "j": e.j,
                    "T_i_j": e.T_i_j.tolist(),
                    "information": e.information.tolist(),
                    "kind": e.kind,
                    "tag": e.tag,
                }
                for e in self.edges
            ],
        }

    @classmethod
    def from_state_dict(cls, cfg: BackendConfig, state: dict) -> PoseGraph:
        g = cls(cfg)
        for k, v in state["nodes"].items():
            g.add_node(int(k), np.array(v))
        g.anchors = {int(k) for k in state.get("anchors", [])}
        for e in state["edges"]:
            g.add_edge(
                Edge(
                    e["i"],
                    e["j"],
                    np.array(e["T_i_j"]),
                    np.array(e["information"]),
                    e["kind"],
                    e.get("tag", -1),
                )
            )
        return g

    def to_g2o(self) -> str:
        """The graph in g2o's text format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT with the upper
        triangle of the information in g2o's translation-first order); loop edges are the ones
        between non-consecutive keyframes. The first vertex is fixed (FIX)."""
        lines = []
        for key in sorted(self.nodes):
            v = pose_to_tum(self.nodes[key])
            pose = " ".join(f"{x:.9f}" for x in v)
            lines.append(f"VERTEX_SE3:QUAT {key} {pose}")
        for key in sorted(self.anchors or ({min(self.nodes)} if self.nodes else set())):
            lines.append(f"FIX {key}")
        iu = np.triu_indices(6)
        for e in self.edges:
            v = pose_to_tum(e.T_i_j)
            info = e.information[np.ix_(_G2O_ORDER, _G2O_ORDER)][iu]
            pose = " ".join(f"{x:.9f}" for x in v)
            upper = " ".join(f"{x:.9g}" for x in info)
            lines.append(f"EDGE_SE3:QUAT {e.i} {e.j} {pose} {upper}")
        return "\n".join(line for line in lines if line) + "\n"

    def write_g2o(self, path: str | Path) -> None:
        atomic_write_text(Path(path), self.to_g2o())
