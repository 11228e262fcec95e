"""Where the frame list is cut."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from slam.chunked.plan import plan_chunks
from slam.errors import ConfigError


def test_chunks_cover_the_frames_once_and_overlap_by_the_overlap():
    chunks = plan_chunks(792, 2, 30)
    assert [(c.start, c.stop, c.keep_stop) for c in chunks] == [(0, 396, 366), (366, 792, 792)]


@given(n=st.integers(1, 5000), k=st.integers(1, 16), overlap=st.integers(1, 60))
def test_every_frame_is_reported_by_exactly_one_chunk(n, k, overlap):
    chunks = plan_chunks(n, k, overlap)
    reported = [i for c in chunks for i in range(c.start, c.keep_stop)]
    assert reported == list(range(n))
    for a, b in zip(chunks, chunks[1:]):
        assert a.stop - b.start == overlap and a.keep_stop == b.start  # tracked by both
        assert b.frames >= 2 * overlap


def test_a_short_sequence_gets_fewer_chunks_and_bad_counts_are_errors():
    assert len(plan_chunks(50, 4, 30)) == 1
    with pytest.raises(ConfigError, match="chunks must be >= 1"):
        plan_chunks(100, 0, 10)
