"""Config values that would crash or silently empty a run (issue 19): non-finite numbers
anywhere in the tree, voxel sizes Open3D's ray-cast cannot take."""

from __future__ import annotations

import dataclasses
import typing

import pytest

from slam.config import SlamConfig, config_from_dict, load_config
from slam.config_ranges import MAX_BLOCK_SIZE_M
from slam.errors import ConfigError


def float_keys(cls: type = SlamConfig, prefix: str = "") -> list[str]:
    """Dotted keys of every float field of the config tree."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out += float_keys(tp, f"{prefix}{f.name}.")
        elif tp is float:
            out.append(f"{prefix}{f.name}")
    return out


def nested(key: str, value) -> dict:
    d: dict = {}
    cur = d
    *sections, last = key.split(".")
    for s in sections:
        cur = cur.setdefault(s, {})
    cur[last] = value
    return d


FLOAT_KEYS = float_keys()


def test_the_tree_has_float_fields_in_every_section():
    assert len(FLOAT_KEYS) > 60
    assert {k.split(".")[0] for k in FLOAT_KEYS} >= {"tracking", "mapping", "loop", "backend", "ba"}


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")], ids=str)
def test_every_float_field_refuses_non_finite_values(value):
    """Each float key of the tree, set to NaN or +-inf: the error names it (comparisons with
    NaN are false, so range checks alone let NaN through; inf passed '> 0')."""
    for key in FLOAT_KEYS:
        with pytest.raises(ConfigError) as info:
            config_from_dict(nested(key, value))
        assert str(info.value) == f"config key '{key}' must be a finite number, got {value!r}"


def test_non_finite_values_set_in_code_are_refused_by_the_slam():
    import slam

    cfg = SlamConfig()
    cfg.tracking.icp.max_correspondence_m = float("nan")
    with pytest.raises(ConfigError, match="'tracking.icp.max_correspondence_m' must be a finite"):
        slam.Slam(cfg)


def test_yaml_inf_and_nan(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("mapping:\n  voxel_size_m: .inf\n")
    with pytest.raises(ConfigError, match=r"c.yaml: config key 'mapping.voxel_size_m' must be a "
                       r"finite number, got inf"):  # fmt: skip
        load_config(p)
    p.write_text("tracking:\n  downsample: .nan\n")
    with pytest.raises(ConfigError, match="'tracking.downsample' must be an integer, got nan"):
        load_config(p)
    p.write_text("tracking:\n  iterations: [4, .inf]\n")
    with pytest.raises(ConfigError, match="'tracking.icp.iterations' must be an integer, got inf"):
        load_config(p)
    p.write_text("dataset:\n  calibration: {fx: .nan}\n")
    with pytest.raises(ConfigError, match="'dataset.calibration.fx' must be a finite number"):
        load_config(p)


@pytest.mark.parametrize("voxel", [0.5, 0.3, 0.1, 0.03])
def test_voxel_sizes_the_ray_cast_cannot_take_are_refused(voxel):
    """0.5 and 0.3 segfaulted in Open3D's ray-cast, .inf ran with an empty map; the bound is
    the block edge voxel_size_m x block_resolution (see MAX_BLOCK_SIZE_M)."""
    with pytest.raises(ConfigError) as info:
        config_from_dict({"mapping": {"voxel_size_m": voxel}})
    assert str(info.value) == (
        "config key 'mapping.voxel_size_m' must be in (0, 0.02] metres with "
        "mapping.block_resolution 8 (e.g. 0.01; a block, voxel_size_m x block_resolution, of at "
        "most 0.16 m: larger blocks make Open3D's ray-cast read uninitialised memory: "
        f"segmentation faults from 0.1 m voxels), got {voxel}"
    )


def test_the_bound_is_on_the_block_edge():
    assert MAX_BLOCK_SIZE_M == 0.16
    assert config_from_dict({"mapping": {"voxel_size_m": 0.02}}).mapping.voxel_size_m == 0.02
    with pytest.raises(ConfigError, match=r"must be in \(0, 0.01\] metres with "
                       r"mapping.block_resolution 16 .*got 0.02"):  # fmt: skip
        config_from_dict({"mapping": {"voxel_size_m": 0.02, "block_resolution": 16}})
    cfg = config_from_dict({"mapping": {"voxel_size_m": 0.04, "block_resolution": 4}})
    assert cfg.mapping.voxel_size_m == 0.04
    with pytest.raises(ConfigError, match="'mapping.block_resolution' must be 4, 8 or 16"):
        config_from_dict({"mapping": {"voxel_size_m": 0.01, "block_resolution": 5}})


@pytest.mark.parametrize(
    "key, value",
    [
        ("tracking.icp.iterations", [1_000_000_000, 1_000_000_000, 1_000_000_000]),
        ("tracking.icp.large_motion_iterations", [12, 8, 101]),
        ("tracking.ransac.iterations", 1_000_000_000),
        ("loop.ransac_iterations", 1_000_000),
        ("backend.max_iterations", 10**9),
        ("ba.max_iterations", 10**9),
    ],
)
def test_counts_no_one_could_mean_are_refused(key, value):
    """A frame of 1e9 iterations per level never ended and ignored SIGTERM; 1e9 RANSAC
    hypotheses took 24 GB: counts have an upper bound, named in the error."""
    with pytest.raises(ConfigError, match=rf"config key '{key}' must be .*in \[\d, \d+\]"):
        config_from_dict(nested(key, value))
