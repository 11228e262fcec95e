import pytest

from slam.config import SlamConfig, config_from_dict, load_config
from slam.errors import ConfigError


def test_defaults_round_trip_through_yaml(tmp_path):
    cfg = SlamConfig()
    p = tmp_path / "c.yaml"
    p.write_text(cfg.to_yaml())
    assert load_config(p) == cfg


def test_partial_override():
    cfg = config_from_dict(
        {"mapping": {"voxel_size_m": 0.02}, "tracking": {"ransac": {"iterations": 50}}}
    )
    assert cfg.mapping.voxel_size_m == 0.02
    assert cfg.tracking.ransac.iterations == 50
    assert cfg.tracking.downsample == SlamConfig().tracking.downsample


@pytest.mark.parametrize(
    "data, match",
    [
        ({"mapping": {"voxel": 1}}, "unknown config key"),
        ({"mapping": {"voxel_size_m": "big"}}, "must be a number"),
        ({"tracking": {"downsample": 1.5}}, "must be an integer"),
        ({"tracking": []}, "must be a mapping"),
        ({"output": {"save_mesh": "yes"}}, "true/false"),
    ],
)
def test_invalid_values_are_errors(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "none.yaml")


@pytest.mark.parametrize(
    "data, match",
    [
        ({"mapping": {"voxel_size_m": 0}}, r"'mapping.voxel_size_m' must be in \(0, 0.02\] .*got 0"),
        ({"mapping": {"voxel_size_m": -0.01}}, r"'mapping.voxel_size_m' must be in \(0, 0.02\]"),
        ({"tracking": {"depth_max_m": -1}}, r"'tracking.depth_max_m' must be > tracking.depth_min_m"),
        ({"tracking": {"iterations": []}}, r"'tracking.iterations' must be a non-empty list"),
        ({"tracking": {"iterations": [0, 0]}}, r"'tracking.iterations' must be counts in \[0, 100\]"),
        ({"tracking": {"iterations": [4, 2]}}, r"'tracking.large_motion_iterations' must be one count per level of tracking.iterations \(2 levels\)"),
        ({"dataset": {"stride": 0}}, r"'dataset.stride' must be >= 1"),
        ({"dataset": {"max_frames": 0}}, r"'dataset.max_frames' must be >= 1"),
        ({"backend": {"loop_kernel": "tukey"}}, r"'backend.loop_kernel' must be cauchy, huber"),
        ({"tracking": {"min_overlap": 2}}, r"'tracking.min_overlap' must be in \[0, 1\]"),
    ],
)
def test_out_of_range_values_name_the_key(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data)


def test_out_of_range_values_in_code_are_caught_by_the_run():
    import slam

    cfg = SlamConfig()
    cfg.mapping.voxel_size_m = 0.0
    with pytest.raises(ConfigError, match="mapping.voxel_size_m"):
        slam.Slam(cfg)


def test_unknown_key_suggests_the_right_one():
    with pytest.raises(ConfigError, match="did you mean 'voxel_size_m' for 'voxel_size'"):
        config_from_dict({"mapping": {"voxel_size": 0.01}})
    with pytest.raises(ConfigError, match="'join_verifications' belongs in section 'loop'"):
        config_from_dict({"dataset": {"join_verifications": 2}})


def test_every_yaml_the_project_ships_loads():
    """Each config YAML under benchmarks/ loads (colour_step_full.yaml named a removed key);
    each bench suite under scripts/ loads as a suite."""
    from pathlib import Path

    from slam.tools.bench_suite import load_suite

    root = Path(__file__).resolve().parents[1]
    configs = sorted((root / "benchmarks").glob("*.yaml"))
    suites = sorted((root / "scripts").glob("*.yaml"))
    assert configs and suites
    for path in configs:
        load_config(path)
    for path in suites:
        load_suite(path)
