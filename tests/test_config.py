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
