"""Runs on the real sequences in ../shared/datasets (skipped with the reason when absent)."""

import pytest

import slam
from slam.config import config_from_dict
from tests.conftest import shared_sequence

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def test_7scenes_first_200_frames():
    seq = slam.open_sequence(shared_sequence("7scenes-1000"))
    res = slam.run(seq, config_from_dict({"dataset": {"max_frames": 200}}))
    m = res.metrics
    assert m["tracking_failures"] == 0
    assert m["ate_rmse_m"] < 0.035, m["ate_rmse_m"]


def test_cabinet_keyframes_end_to_end():
    seq = slam.open_sequence(shared_sequence("tum-fr3-cabinet-kf58"))
    res = slam.run(seq)
    m = res.metrics
    assert m["frames"] == 58
    # large inter-frame motion: RANSAC must seed ICP on a good share of the frames
    assert m["tracking_paths"].get("ransac+icp", 0) >= 10
    assert m["tracking_failures"] <= 5
    # guard: better than Open3D's dense SLAM here (0.53 m, docs/benchmarks.md); runs measured
    # 0.23-0.43 m. The target, 0.10 m, is not met yet.
    assert m["ate_rmse_m"] < 0.53, m["ate_rmse_m"]
