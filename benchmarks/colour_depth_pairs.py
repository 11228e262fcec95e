"""Colour against depth, frame to frame: consecutive frames aligned from their true motion, by
depth alone and by colour joining depth, with how far each lands off the truth and off itself.

    python benchmarks/colour_depth_pairs.py                    # registered-colour rows, x2 kinds
    python benchmarks/colour_depth_pairs.py --only tum-fr1-xyz --weights 0,0.1,1,10
    python benchmarks/colour_depth_pairs.py --only room-x2 --noise 8,2 --vignette 0.5

Whole runs cannot say whether the colour term is a better measurement than depth: a frame's
step mixes its alignment with the model, the keyframes' colour and the motion checks. Here the
frames of each triplet ``(i - 2, i - 1, i)`` are aligned pairwise, frame to frame, each pair
starting at its ground-truth step (so basins and predictions play no part), with the default
config's alignments: ``PreparedFrame.icp_to`` (depth alone: Open3D's ICP) and
``PreparedFrame.joint_to`` at each photometric ``--weights`` (both colour cameras placed along
the true step, as tracking places them along its estimate). Weight 0 is the joint alignment's
own geometric term alone: what colour adds is read against it.

Two errors, in mm of translation:
- the step ``i - 1 -> i`` against the ground truth (it includes the ground truth's own error);
- the cycle error, which needs no ground truth: the steps ``i - 2 -> i - 1`` and
  ``i - 1 -> i`` composed, against ``i - 2 -> i`` aligned directly (a measurement's scatter; a
  bias common to the three cancels).

Only rows whose colour is registered to depth. ``--shift``, ``--radial``, ``--blur``,
``--motion-blur``, ``--noise``, ``--vignette``, ``--gain`` and ``--jpeg`` alter the colour
images first (:class:`Alteration`), and ``--gloss`` adds a fixed light's reflection
(:class:`Gloss`): what a real camera's colour may have that the generator's lacks.
``--color-dt-scale`` and ``--color-dt-add-ms`` move the colour's instant. ``--exact`` adds the
matrix's exact-depth rows (clean normals for ``--gloss``). Writes
``results/colour-depth-pairs[-TAG].json`` and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging

import cv2
import numpy as np
from common import machine, write_result
from matrix import EXACT, real_rows, synthetic_rows

import slam
from slam.data.base import Frame
from slam.frontend.motion import colour_motion
from slam.frontend.pointcloud import normal_map
from slam.frontend.tracker import Tracker
from slam.frontend.weighted_icp import vertex_map
from slam.geometry import inv_T, translation_norm

KINDS = ("room", "wall", "corridor", "hall", "desk")


@dataclasses.dataclass(frozen=True)
class Alteration:
    """What is done to each colour image before it is aligned, in this order: a shift against
    the depth (pixels), a radial displacement against the depth (``radial_px`` at the corners,
    growing as r^2: colour registered to depth only at the centre), a blur (pixels), a line blur of up to ``motion_blur_px`` whose length and
    direction are drawn per frame, vignetting (brightness falls by this fraction at the
    corners), grey noise (grey levels, correlated over ``noise_corr_px``), an exposure gain
    drawn per frame (log-normal, this sigma: auto-exposure) and a JPEG re-encoding of this
    quality (0: none). The frame's colour time offset ``color_dt_s`` becomes
    ``color_dt_s * color_dt_scale + color_dt_add_s``: where tracking places its colour camera."""

    shift_px: tuple[float, float] = (0.0, 0.0)
    blur_px: float = 0.0
    noise: float = 0.0
    noise_corr_px: float = 0.0
    vignette: float = 0.0
    jpeg_quality: int = 0
    gain: float = 0.0
    color_dt_scale: float = 1.0
    color_dt_add_s: float = 0.0
    motion_blur_px: float = 0.0
    radial_px: float = 0.0

    def apply(self, frame: Frame) -> Frame:
        if (self.color_dt_scale, self.color_dt_add_s) != (1.0, 0.0):
            dt = frame.color_dt_s * self.color_dt_scale + self.color_dt_add_s
            frame = dataclasses.replace(frame, color_dt_s=dt)
        c = frame.color
        timing = {"color_dt_scale": 1.0, "color_dt_add_s": 0.0}
        if c is None or dataclasses.replace(self, **timing) == Alteration():
            return frame
        h, w = c.shape[:2]
        img = c.astype(np.float32)
        if self.shift_px != (0.0, 0.0):
            A = np.float32([[1, 0, self.shift_px[0]], [0, 1, self.shift_px[1]]])
            img = cv2.warpAffine(img, A, (w, h), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        y, x = np.mgrid[0:h, 0:w].astype(np.float32)
        dx, dy = x - w / 2, y - h / 2
        r2 = (dx**2 + dy**2) / ((w / 2) ** 2 + (h / 2) ** 2)  # 1 at the corners
        if self.radial_px != 0:  # colour registered to depth only at the centre
            k = np.float32(self.radial_px) * r2 / np.maximum(np.sqrt(dx**2 + dy**2), 1e-6)
            img = cv2.remap(img, x - k * dx, y - k * dy, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        if self.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_px)
        if self.motion_blur_px > 0:
            img = _motion_blur(img, self.motion_blur_px, np.random.default_rng((frame.index, 2)))
        if self.vignette > 0:
            img *= (1.0 - self.vignette * r2)[..., None]
        if self.noise > 0:
            n = np.random.default_rng(frame.index).standard_normal((h, w)).astype(np.float32)
            if self.noise_corr_px > 0:
                n = cv2.GaussianBlur(n, (0, 0), self.noise_corr_px)
                n /= max(float(n.std()), 1e-9)
            img += self.noise * n[..., None]
        if self.gain > 0:
            rng = np.random.default_rng((frame.index, 1))
            img *= np.float32(np.exp(self.gain * rng.standard_normal()))
        c = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if self.jpeg_quality > 0:
            _, buf = cv2.imencode(".jpg", np.ascontiguousarray(c[..., ::-1]),
                                  [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)])  # fmt: skip
            c = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
        return dataclasses.replace(frame, color=c)


def _motion_blur(img: np.ndarray, max_px: float, rng: np.random.Generator) -> np.ndarray:
    """A line blur centred on each pixel, of a length drawn within ``max_px`` along a direction
    drawn per frame: a camera whose motion during the exposure changes from frame to frame."""
    length = rng.uniform(0.0, max_px)
    if length < 0.5:
        return img
    angle = rng.uniform(0.0, np.pi)
    r = int(np.ceil(length / 2)) + 1
    kernel = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    for s in np.linspace(-length / 2, length / 2, 4 * int(np.ceil(length)) + 1):
        x, y = r + s * np.cos(angle), r + s * np.sin(angle)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    kernel /= kernel.sum()
    return cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)


@dataclasses.dataclass(frozen=True)
class Gloss:
    """A white light at a fixed place in the world reflected by every surface (Blinn-Phong):
    ``strength`` x 255 grey levels added where the surface mirrors the light into the camera,
    falling as ``cos^shininess`` of the half-vector's angle away from it. Appearance that
    changes with the viewpoint (a glossy desk, a lit painted wall), which the generator's
    colour lacks. Surface normals from the depth smoothed over a few pixels (the surface's,
    not the depth noise's)."""

    strength: float = 0.0
    shininess: float = 30.0

    def apply(self, frame: Frame, T_world_cam: np.ndarray, light_world: np.ndarray) -> Frame:
        if self.strength <= 0 or frame.color is None:
            return frame
        V = vertex_map(frame.depth_m, frame.K)
        n = normal_map(cv2.GaussianBlur(V, (0, 0), 3.0))
        light = (inv_T(T_world_cam) @ np.append(light_world, 1.0))[:3].astype(np.float32)

        def unit(a: np.ndarray) -> np.ndarray:
            return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-9)

        half = unit(unit(light - V) + unit(-V))
        cos = np.clip(np.einsum("ijk,ijk->ij", n, half), 0.0, 1.0)
        spec = self.strength * 255.0 * cos**self.shininess
        spec[frame.depth_m <= 0] = 0.0
        img = frame.color.astype(np.float32) + spec[..., None]
        color = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return dataclasses.replace(frame, color=color)


#: The frame pairs of a triplet (i - 2, i - 1, i) that are aligned: two steps and their sum.
PAIRS = ((0, 1), (1, 2), (0, 2))


def _align(prepared, frames, pair, step, weight, cfg, levels) -> np.ndarray:
    """``T_a_b`` of the pair ``(a, b)`` of the triplet, aligned from its true ``step``: depth
    alone (``weight`` None) or colour joining depth at ``weight``, both colour cameras placed
    along the true step."""
    a, b = pair
    pa, pb = prepared[a], prepared[b]
    if weight is None:
        return pb.icp_to(pa.pyramid, step, cfg.tracking).T_target_source
    dt = frames[b].timestamp - frames[a].timestamp
    pa.T_depth_colour = colour_motion(step, dt, frames[a].color_dt_s)
    pb.T_depth_colour = colour_motion(step, dt, frames[b].color_dt_s)
    target = pa.photometric_image(levels)
    return pb.joint_to(target, step, cfg.tracking, weight, pa.T_depth_colour).T_target_source


def registered_sequence(path):
    """``(cfg, seq, poses, tracker)``: the default config, the sequence, its ground-truth poses
    by timestamp (rounded to the microsecond) and tracking's frame preparation; None when the
    sequence has no ground truth or its colour is not registered to depth."""
    cfg = slam.load_config(None)
    seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
    gt = seq.ground_truth
    if gt is None or not seq.color_registered:
        return None
    poses = {round(float(t), 6): T for t, T in zip(gt.timestamps, gt.poses)}
    return cfg, seq, poses, Tracker(cfg.tracking, seq.has_color, seq.color_registered)


def pair_errors(
    path,
    weights: list[float],
    every: int,
    alteration: Alteration = Alteration(),
    gloss: Gloss = Gloss(),
) -> dict[str, np.ndarray] | None:
    """Per triplet ``(i - 2, i - 1, i)``, every ``every`` frames: the true step ``i - 1 -> i``
    (mm), the error (mm) of its alignment by depth alone (``depth``) and by each weight's joint
    alignment (``w<weight>``), and each one's cycle error (``<key>_cycle``, mm: the two steps
    against the pair ``i - 2 -> i`` aligned directly; no ground truth in it). None when colour
    is not registered to depth."""
    opened = registered_sequence(path)
    if opened is None:
        return None
    cfg, seq, poses, tracker = opened
    # the light of --gloss: 1 m above and 1 m ahead of where the camera starts (y is down)
    light = (seq.ground_truth.poses[0] @ np.array([0.0, -1.0, 1.0, 1.0]))[:3]
    levels = len(cfg.tracking.iterations)
    keys = ["depth"] + [f"w{w:g}" for w in weights]
    out: dict[str, list[float]] = {"true_step": []}
    out.update({k: [] for k in keys})
    out.update({f"{k}_cycle": [] for k in keys})
    for i in range(max(every, 2), len(seq), every):
        stamps = [round(seq.timestamp(k), 6) for k in (i - 2, i - 1, i)]
        if any(t not in poses for t in stamps):
            continue
        frames = [alteration.apply(seq[k]) for k in (i - 2, i - 1, i)]
        frames = [gloss.apply(f, poses[t], light) for f, t in zip(frames, stamps)]
        prepared = [tracker.prepare(f) for f in frames]
        for p in prepared:
            p.photometric_image(levels)
        steps = {(a, b): inv_T(poses[stamps[a]]) @ poses[stamps[b]] for a, b in PAIRS}
        out["true_step"].append(translation_norm(steps[(1, 2)]) * 1e3)
        for key, weight in [("depth", None)] + [(f"w{w:g}", w) for w in weights]:
            found = {pair: _align(prepared, frames, pair, steps[pair], weight, cfg, levels)
                     for pair in PAIRS}  # fmt: skip
            # the pair (i - 1, i) against the truth; the triangle against itself (no truth)
            out[key].append(translation_norm(inv_T(steps[(1, 2)]) @ found[(1, 2)]) * 1e3)
            loop = inv_T(found[(0, 2)]) @ found[(0, 1)] @ found[(1, 2)]
            out[f"{key}_cycle"].append(translation_norm(loop) * 1e3)
    return {k: np.asarray(v) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="0,1,10", help="photometric weights of the joint runs")
    ap.add_argument("--every", type=int, default=4, help="every n-th triplet")
    ap.add_argument("--frames", type=int, default=240, help="frames of each synthetic row")
    ap.add_argument("--only", default="", help="comma-separated substrings of row names")
    ap.add_argument("--shift", default="0,0", help="dx,dy: shift the colour images (pixels)")
    ap.add_argument("--blur", type=float, default=0.0, help="blur the colour images (pixels)")
    ap.add_argument(
        "--noise", default="0,0", help="sigma,corr: grey noise (levels), correlated (px)"
    )
    ap.add_argument("--vignette", type=float, default=0.0, help="brightness loss at the corners")
    ap.add_argument("--jpeg", type=int, default=0, help="re-encode the colour as JPEG (quality)")
    ap.add_argument("--gain", type=float, default=0.0, help="per-frame exposure gain (log sigma)")
    ap.add_argument(
        "--color-dt-scale",
        type=float,
        default=1.0,
        help="scale each frame's colour time offset (0: colour taken at the depth's instant)",
    )
    ap.add_argument(
        "--color-dt-add-ms",
        type=float,
        default=0.0,
        help="add this to each frame's colour time offset (milliseconds)",
    )
    ap.add_argument(
        "--motion-blur",
        type=float,
        default=0.0,
        help="a line blur of up to this many pixels, its length and direction drawn per frame",
    )
    ap.add_argument(
        "--gloss",
        default="0,30",
        help="strength,shininess: a fixed light's reflection added to the colour (0: none)",
    )
    ap.add_argument(
        "--radial",
        type=float,
        default=0.0,
        help="colour moved outwards against depth by this many pixels at the corners (r^2)",
    )
    ap.add_argument("--exact", action="store_true", help="also the matrix's exact-depth rows")
    ap.add_argument("--tag", default="", help="suffix of the result name")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    weights = [float(w) for w in args.weights.split(",")]
    dx, dy = (float(v) for v in args.shift.split(","))
    sigma, corr = (float(v) for v in args.noise.split(","))
    alteration = Alteration(
        (dx, dy),
        args.blur,
        sigma,
        corr,
        args.vignette,
        args.jpeg,
        args.gain,
        args.color_dt_scale,
        args.color_dt_add_ms * 1e-3,
        args.motion_blur,
        args.radial,
    )
    strength, shininess = (float(v) for v in args.gloss.split(","))
    gloss = Gloss(strength, shininess)
    exact = EXACT if args.exact else ()
    rows = real_rows() + synthetic_rows(args.frames, KINDS, (2.0,), (0,), exact=exact)
    if args.only:
        rows = [r for r in rows if any(s in r.name for s in args.only.split(","))]
    keys = ["depth"] + [f"w{w:g}" for w in weights]
    print("| sequence | pairs | true step mm | " + " | ".join(keys) + " | cycle: "
          + " | ".join(keys) + " (median / p90 mm) |")  # fmt: skip
    print("|---|---|---|" + "---|" * 2 * len(keys))
    out = {}
    for row in rows:
        errors = pair_errors(row.path, weights, args.every, alteration, gloss)
        if errors is None:
            continue
        summary = {
            k: {
                "median": round(float(np.median(v)), 3),
                "p90": round(float(np.percentile(v, 90)), 3),
            }
            for k, v in errors.items()
        }
        out[row.name] = {"pairs": len(errors["depth"]), "mm": summary}
        cells = " | ".join(
            f"{summary[k]['median']:.2f} / {summary[k]['p90']:.2f}"
            for k in keys + [f"{k}_cycle" for k in keys]
        )
        step = summary["true_step"]["median"]
        print(f"| {row.name} | {len(errors['depth'])} | {step:.1f} | {cells} |")
    settings = {"weights": weights, "every": args.every, **dataclasses.asdict(alteration)}
    settings["gloss"] = dataclasses.asdict(gloss)
    name = "colour-depth-pairs" + (f"-{args.tag}" if args.tag else "")
    path = write_result(name, {"machine": machine(), "settings": settings, "rows": out})
    print(f"written: {path}")


if __name__ == "__main__":
    main()
