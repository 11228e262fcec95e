"""Where a run's frame list is cut into chunks."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from slam.errors import ConfigError


@dataclass(frozen=True)
class Chunk:
    """Chunk ``number`` tracks positions ``[start, stop)`` of the run's frame list and reports
    ``[start, keep_stop)``: its last ``stop - keep_stop`` frames are the next chunk's first
    ones (the overlap through which the two are chained), reported by the next chunk."""

    number: int
    start: int
    stop: int
    keep_stop: int

    @property
    def frames(self) -> int:
        return self.stop - self.start

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


def plan_chunks(n_frames: int, chunks: int, overlap: int) -> list[Chunk]:
    """``chunks`` chunks of about equal length over ``n_frames`` frames; each after the first
    starts ``overlap`` frames before the previous one ends. Fewer chunks when the frames are
    too few for each to hold at least twice the overlap."""
    if chunks < 1:
        raise ConfigError(f"the number of chunks must be >= 1, got {chunks}")
    if overlap < 1 and chunks > 1:
        raise ConfigError(f"chunks must overlap by >= 1 frame, got {overlap}")
    chunks = max(1, min(chunks, n_frames // max(2 * overlap, 1)))
    bounds = [round(k * n_frames / chunks) for k in range(chunks + 1)]
    out = []
    for k in range(chunks):
        start = 0 if k == 0 else bounds[k] - overlap
        last = k == chunks - 1
        out.append(Chunk(k, start, bounds[k + 1], n_frames if last else bounds[k + 1] - overlap))
    return out
