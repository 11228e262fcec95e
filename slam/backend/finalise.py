"""The end of a run: the final keyframe poses (pose graph, then bundle adjustment) and every
frame bent onto them (:func:`elastic_correction`)."""

from __future__ import annotations

import numpy as np

from slam.geometry import exp_se3, inv_T, log_se3


def elastic_correction(
    odometry: np.ndarray,
    kf_positions: list[int],
    T_world_kf_odometry: list[np.ndarray],
    T_world_kf_corrected: list[np.ndarray],
    runs: np.ndarray | None = None,
) -> np.ndarray:
    """Corrected poses of every frame from the corrected keyframe poses.

    ``odometry`` (N, 4, 4): frontend poses of all frames; ``kf_positions``: the row of each
    keyframe in ``odometry`` (increasing). A frame between keyframes a and b keeps its odometry
    pose relative to each of them, giving two estimates ``T_a' T_a^-1 T`` and ``T_b' T_b^-1 T``;
    it takes their SE(3) interpolation at its fraction of the way from a to b, so the
    trajectory bends smoothly and keyframes land exactly on their optimised poses.

    ``runs`` (N,): the tracking run of each frame (a run ends where tracking was lost). Frames
    follow keyframes of their own run only: odometry says nothing across a loss. Every run
    starts with a keyframe.
    """
    out = odometry.copy()
    if not kf_positions:
        return out
    runs = np.zeros(len(odometry), int) if runs is None else np.asarray(runs)
    corr = [Tc @ inv_T(To) for Tc, To in zip(T_world_kf_corrected, T_world_kf_odometry)]
    n = len(odometry)
    for f in range(0, kf_positions[0]):
        out[f] = corr[0] @ odometry[f]
    for k, a in enumerate(kf_positions):
        nxt = kf_positions[k + 1] if k + 1 < len(kf_positions) else n
        same_run = k + 1 < len(kf_positions) and runs[nxt] == runs[a]
        for f in range(a, nxt):
            Ta = corr[k] @ odometry[f]
            if not same_run:
                out[f] = Ta
                continue
            Tb = corr[k + 1] @ odometry[f]
            s = (f - a) / (nxt - a)
            out[f] = Ta @ exp_se3(s * log_se3(inv_T(Ta) @ Tb))
    return out
