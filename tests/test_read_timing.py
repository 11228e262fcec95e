"""Issue 19, item 12: the run's time and speed include the frames it could not read, and the
reader thread's own time per frame is reported (``read_ms_per_frame``) beside the loop's wait
for frames (``stage_ms_*["load"]``)."""

from __future__ import annotations

import threading

import pytest

import slam
from slam.config import config_from_dict
from slam.errors import FrameReadError

SLEEP_S = 0.3


@pytest.fixture(scope="module")
def tiny_seq(tmp_path_factory):
    from slam.synthetic import SynthConfig, generate_sequence

    root = tmp_path_factory.mktemp("readtiming")
    return generate_sequence(root / "seq", SynthConfig.half_resolution(frames=300, render_frames=6))


def _first_frame_slow_and_unreadable(seq):
    """The sequence, whose frame 0 takes SLEEP_S to fail in the reader thread (the pre-flight
    check, in the main thread, reads it at once)."""
    base = type(seq)

    class Slow(base):  # type: ignore[misc, valid-type]
        def __getitem__(self, index):
            if index == 0 and threading.current_thread().name.startswith("slam-read"):
                threading.Event().wait(SLEEP_S)
                raise FrameReadError("frame 0: unreadable (test)")
            return base.__getitem__(self, index)

    seq.__class__ = Slow
    return seq


def test_unreadable_frames_count_in_seconds_fps_and_read_time(tiny_seq):
    seq = _first_frame_slow_and_unreadable(slam.open_sequence(tiny_seq))
    res = slam.run(seq, config_from_dict({"dataset": {"max_frames": 6}}))
    m = res.metrics
    assert m["frames"] == 5 and m["frames_skipped"] == 1
    total = m["stage_ms_total"]
    # the loop waited for the unreadable first frame: that wait is in `load`, so in the loop time
    assert total["load"] >= 0.8 * SLEEP_S * 1e3
    loop_s = sum(total[k] for k in ("load", "tracking", "integration", "loop")) / 1e3
    assert m["seconds"] >= loop_s >= 0.8 * SLEEP_S
    # fps: every frame the loop went through (read or skipped) over the loop's time
    assert m["fps"] == pytest.approx(6 / loop_s, rel=1e-3)
    # real-time factor: the 5 stepped frames span 4 intervals, 5 with the last frame's own
    stamps = [s.timestamp for s in res.tracking]
    duration = (stamps[-1] - stamps[0]) * 5 / 4
    assert m["real_time_factor"] == pytest.approx(duration / loop_s, rel=2e-2)
    # the reader thread's own time, per frame it read (the unreadable one included)
    assert m["read_ms_per_frame"] is not None
    assert m["read_ms_per_frame"] * 6 >= SLEEP_S * 1e3
    assert list(m).index("read_ms_per_frame") == list(m).index("peak_rss_mb") + 1


def test_stepwise_system_as_the_readme_streams_it(tiny_seq):
    """README's streaming example: a Sequence iterates Frames into Slam.step; finish() knows no
    ground truth (no accuracy keys) and no reader (no ``read_ms_per_frame``);
    evaluate_against_ground_truth adds what slam.run adds."""
    from slam.pipeline import evaluate_against_ground_truth

    seq = slam.open_sequence(tiny_seq)
    system = slam.Slam(
        slam.SlamConfig(), has_color=seq.has_color, color_registered=seq.color_registered
    )
    for frame in seq:
        assert isinstance(frame, slam.Frame)
        system.step(frame)
    result = system.finish()
    assert "read_ms_per_frame" not in result.metrics and "ate_rmse_m" not in result.metrics
    result.metrics.update(evaluate_against_ground_truth(seq, result.trajectory, result.odometry))
    assert 0 <= result.metrics["ate_rmse_m"] < 0.05
