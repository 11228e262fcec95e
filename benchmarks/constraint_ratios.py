"""How blind each sequence's depth is: the distribution of the frames' constraint ratios.

    python benchmarks/constraint_ratios.py                       # shared real + x1 seed-0 kinds
    python benchmarks/constraint_ratios.py --only wall,tum --samples 60

The ratio is the one tracking computes for every frame before aligning it
(``PreparedFrame.constraint_ratio``: :func:`slam.frontend.weighted_icp.depth_constraint` on the
frame's own depth, the default config): the weakest direction's standard deviation over the
strongest's. Colour joins depth above ``tracking.photometric_ratio``. Writes
``results/constraint-ratios.json`` (percentiles 10/50/90/100 and the fraction of frames above 5,
8, 12 and 20 per sequence) and prints a table. No tracking is run: a few seconds a sequence.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import machine, write_result
from matrix import real_rows, synthetic_rows

import slam
from slam.frontend.frame import PreparedFrame

THRESHOLDS = (5.0, 8.0, 12.0, 20.0)


def ratios(path, samples: int) -> np.ndarray:
    """The constraint ratios of ``samples`` frames spread evenly over the sequence."""
    cfg = slam.load_config(None)
    seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
    idx = np.unique(np.linspace(0, len(seq) - 1, min(samples, len(seq))).astype(int))
    return np.array(
        [PreparedFrame.build(seq[int(i)], cfg.tracking, None).constraint_ratio for i in idx]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=120, help="frames per sequence")
    ap.add_argument("--frames", type=int, default=240, help="frames of each synthetic row")
    ap.add_argument("--only", default="", help="comma-separated substrings of row names")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    kinds = ("room", "wall", "corridor", "hall", "desk")
    rows = real_rows() + synthetic_rows(args.frames, kinds, (1.0,), (0,))
    if args.only:
        rows = [r for r in rows if any(s in r.name for s in args.only.split(","))]
    out = {}
    print("| sequence | ratio 10 / 50 / 90 / max | " + " | ".join(f"> {t:g}" for t in THRESHOLDS) + " |")
    print("|---|---|" + "---|" * len(THRESHOLDS))
    for row in rows:
        r = ratios(row.path, args.samples)
        pct = [round(float(v), 2) for v in np.percentile(r, [10, 50, 90, 100])]
        above = {f"{t:g}": round(float(np.mean(r > t)), 3) for t in THRESHOLDS}
        out[row.name] = {"frames": len(r), "percentiles_10_50_90_100": pct, "fraction_above": above}
        cells = " | ".join(f"{100 * v:.0f}%" for v in above.values())
        print(f"| {row.name} | {' / '.join(f'{v:.1f}' for v in pct)} | {cells} |")
    path = write_result("constraint-ratios", {"machine": machine(), "rows": out})
    print(f"written: {path}")


if __name__ == "__main__":
    main()
