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
        ({"tracking": {"icp": {"iterations": []}}}, r"'tracking.icp.iterations' must be a non-empty list"),
        ({"tracking": {"icp": {"iterations": [0, 0]}}}, r"'tracking.icp.iterations' must be counts in \[0, 100\]"),
        ({"tracking": {"icp": {"iterations": [4, 2]}}}, r"'tracking.icp.large_motion_iterations' must be one count per level of tracking.icp.iterations \(2 levels\)"),
        ({"dataset": {"stride": 0}}, r"'dataset.stride' must be >= 1"),
        ({"dataset": {"max_frames": 0}}, r"'dataset.max_frames' must be >= 1"),
        ({"backend": {"loop_kernel": "tukey"}}, r"'backend.loop_kernel' must be cauchy, huber"),
        ({"tracking": {"icp": {"min_overlap": 2}}}, r"'tracking.icp.min_overlap' must be in \[0, 1\]"),
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
    """Each config YAML under benchmarks/ loads;
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


def test_a_tracking_key_written_before_the_sub_sections_is_read_from_its_new_place(caplog):
    """`tracking.max_correspondence_m` is `tracking.icp.max_correspondence_m` now: an older file
    (a run folder's config.yaml) still loads, with a warning naming the new key; one key given
    in both places is an error."""
    import logging

    with caplog.at_level(logging.WARNING):
        cfg = config_from_dict({"tracking": {"max_correspondence_m": 0.05, "gap_factor": 3.0,
                                             "downsample": 1, "ransac": {"iterations": 50}}})  # fmt: skip
    assert cfg.tracking.icp.max_correspondence_m == 0.05 and cfg.tracking.motion.gap_factor == 3.0
    assert cfg.tracking.downsample == 1 and cfg.tracking.ransac.iterations == 50
    assert "'tracking.max_correspondence_m' is now 'tracking.icp.max_correspondence_m'" in caplog.text
    with pytest.raises(ConfigError, match="max_correspondence_m.*belongs in section 'tracking.icp'"):
        config_from_dict({"tracking": {"max_correspondence_m": 0.05,
                                       "icp": {"max_correspondence_m": 0.04}}})  # fmt: skip
