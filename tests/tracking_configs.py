"""Tracking configurations for tests, keys named flat: ``tracking_config(min_overlap=0.7)`` sets
``tracking.icp.min_overlap`` (each key lives in one section of TrackingConfig)."""

from __future__ import annotations

import dataclasses
from typing import Any

from slam.config import TrackingConfig

SECTIONS = ("icp", "motion", "colour", "recovery")


def tracking_config(**keys: Any) -> TrackingConfig:
    cfg = TrackingConfig()
    top = {f.name for f in dataclasses.fields(cfg)}
    for name, value in keys.items():
        if name in top:
            cfg = dataclasses.replace(cfg, **{name: value})
            continue
        (section,) = [s for s in SECTIONS if hasattr(getattr(cfg, s), name)]
        sub = dataclasses.replace(getattr(cfg, section), **{name: value})
        cfg = dataclasses.replace(cfg, **{section: sub})
    return cfg
