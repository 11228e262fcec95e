"""What tracking needs of the map, as structural types.

The frontend must not import :mod:`slam.mapping` (and mapping never imports the frontend): the
tracker only ever ray-casts the model at a guessed pose, so that one call is all it asks for.
:class:`slam.mapping.submaps.SubmapMap` and :class:`slam.mapping.tsdf.TSDFVolume` satisfy
:class:`TrackingModel` as they are; a test can pass any object with such a ``raycast``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class ModelView(Protocol):
    """A ray-cast view of the model (e.g. :class:`slam.mapping.tsdf.Rendering`): depth in metres
    (0 = no surface) and, when asked for and the model has it, colour (float RGB in [0, 1])."""

    @property
    def depth_m(self) -> np.ndarray: ...

    @property
    def color(self) -> np.ndarray | None: ...


class TrackingModel(Protocol):
    """The model the tracker aligns frames to: it renders itself from a camera pose.

    ``K``, ``width``, ``height``: the tracking-resolution camera; ``T_world_cam``: the guessed
    pose; ``frustum_depth_m``: the frame's depth at that resolution, which bounds the rays to the
    blocks the frame can see (the model decides how to use it); ``min_weight``: surfaces fused
    with less weight are not rendered (None: the model's own threshold). ``depth_max_m``: depth
    beyond this is never fused, so the model cannot hold what the frame sees beyond it."""

    @property
    def depth_max_m(self) -> float: ...

    def raycast(
        self,
        K: np.ndarray,
        width: int,
        height: int,
        T_world_cam: np.ndarray,
        with_normals: bool = ...,
        with_color: bool = ...,
        *,
        frustum_depth_m: np.ndarray | None = ...,
        min_weight: float | None = ...,
    ) -> ModelView: ...
