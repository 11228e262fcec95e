"""ORB landmarks: keyframe features associated into tracks, one track per physical point.

Each new keyframe is matched against a few earlier keyframes of the same map: the previous
``ba.match_window`` keyframes and up to ``ba.match_nearby`` others whose poses lie close to it
(a revisit the camera made without a detected loop, e.g. sweeping back and forth over a desk).
Matching is *guided* by the known relative pose (odometry or the pose graph): each feature of
the older keyframe, lifted by its depth, is projected into the new one and matched only to
features within ``ba.match_radius_px`` of the prediction whose depth agrees, by Hamming
distance with a ratio test among those candidates. The pose makes this both stricter (wrong
matches must also agree geometrically) and more complete (no global ratio test against
a thousand descriptors, which repetitive texture defeats) than descriptor matching alone.

Matched features join the older feature's landmark or start a new landmark together; a feature
matched to two different landmarks merges them (union-find; the ids stay valid, a merged id
resolves to its root). :meth:`LandmarkMap.merge_loop` does the same between the two visits of
an accepted loop with the loop's verified relative pose, so both visits share landmarks.

Landmarks store no position: bundle adjustment initialises each from its observations (pixel
and depth) under the poses it starts from, so loop corrections never leave stale points behind.
Everything is numpy over arrays of features (no Python loop per feature); the per-keyframe cost
is a few guided matchings of ~1000 features (a k-d tree query each).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from slam.backend.feature_matching import (
    colour_intrinsics,
    distinct_features,
    guided_match,
    match_candidates,
)
from slam.config import BAConfig
from slam.errors import SlamError
from slam.geometry import inv_T
from slam.keyframe import Keyframe

log = logging.getLogger(__name__)


class LandmarkError(SlamError):
    """The landmark map was asked about a keyframe it does not hold."""


class IdForest:
    """Union-find over landmark ids, vectorised: ``root`` resolves arrays of ids at once
    (paths are compressed after every merge, so a lookup is one or two array gathers)."""

    def __init__(self) -> None:
        self.parent = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.parent)

    def new(self, n: int) -> np.ndarray:
        """``n`` fresh ids."""
        ids = np.arange(len(self), len(self) + n, dtype=np.int64)
        self.parent = np.concatenate([self.parent, ids])
        return ids

    def root(self, ids: np.ndarray) -> np.ndarray:
        """The root of each id (-1 stays -1)."""
        ids = np.asarray(ids, np.int64)
        out = ids.copy()
        ok = ids >= 0
        r = out[ok]
        while True:
            p = self.parent[r]
            if np.array_equal(p, r):
                break
            r = p
        out[ok] = r
        return out

    def union(self, a: np.ndarray, b: np.ndarray) -> int:
        """Merge ids ``a[k]`` into ``b[k]``; returns how many merges happened."""
        n = 0
        for x, y in zip(a.tolist(), b.tolist()):  # a handful per keyframe
            rx, ry = int(self.root(np.array([x]))[0]), int(self.root(np.array([y]))[0])
            if rx != ry:
                self.parent[rx] = ry
                n += 1
        if n:
            self.parent = self.root(np.arange(len(self)))
        return n


class LandmarkMap:
    """Landmark tracks over keyframes (see the module docstring).

    ``downsample``: ``tracking.downsample``, to recover the intrinsics of the ORB pixels from
    the keyframes' tracking-resolution ``K``. Keyframes are kept by reference (their features
    are the observations); :meth:`state_dict` saves only the associations.
    """

    def __init__(self, cfg: BAConfig, downsample: int = 2) -> None:
        self.cfg = cfg
        self.downsample = downsample
        self.keyframes: dict[int, Keyframe] = {}
        self.assoc: dict[int, np.ndarray] = {}  # keyframe id -> landmark id per feature (-1)
        self.usable: dict[int, np.ndarray] = {}  # keyframe id -> mask of distinct features
        self.ids = IdForest()  # landmark ids; a merged id resolves to its root
        self.merges = 0  # landmarks merged into others (same physical point found twice)
        self.loop_merges = 0  # feature pairs associated across accepted loops

    def root(self, ids: np.ndarray) -> np.ndarray:
        """The landmark each id stands for now (merged ids resolve to their root; -1 stays)."""
        return self.ids.root(ids)

    # --- building
    def K(self, kf: Keyframe) -> np.ndarray:
        if kf.K is None:
            raise LandmarkError(f"keyframe {kf.id} has no intrinsics")
        return colour_intrinsics(kf.K, self.downsample)

    def add_keyframe(
        self,
        kf: Keyframe,
        poses: Mapping[int, np.ndarray] | None = None,
        same_map: Callable[[Keyframe, Keyframe], bool] | None = None,
    ) -> int:
        """Associate a new keyframe's features with the map's landmarks (see the module
        docstring). ``poses``: current estimates ``T_world_kf`` by keyframe id (the pose
        graph's nodes; default each keyframe's odometry pose); ``same_map``: whether two
        keyframes are in the same map (segments not yet joined have no common frame).
        Returns the number of features now observing a landmark."""
        if kf.id in self.keyframes:
            raise LandmarkError(f"keyframe {kf.id} was already added")
        poses = poses if poses is not None else _odometry_poses(self.keyframes, kf)
        nbrs = (
            match_candidates(self.keyframes.values(), kf, poses, self.cfg, same_map)
            if len(kf.features)
            else []
        )
        self._register(kf)
        if not nbrs:
            return 0
        T_w_a = poses[kf.id]
        pairs = [(o, inv_T(T_w_a) @ poses[o.id]) for o in nbrs]
        n = self._associate(kf, pairs)
        log.debug("keyframe %d: %d features on landmarks (%d neighbours)", kf.id, n, len(nbrs))
        return n

    def _register(self, kf: Keyframe, assoc: np.ndarray | None = None) -> None:
        self.keyframes[kf.id] = kf
        self.assoc[kf.id] = (
            np.full(len(kf.features), -1, np.int64) if assoc is None else assoc.astype(np.int64)
        )
        self.usable[kf.id] = distinct_features(kf.features.pixels)

    def merge_loop(
        self,
        query: int,
        match: int,
        T_match_query: np.ndarray,
        poses: Mapping[int, np.ndarray] | None = None,
        neighbours: int = 2,
    ) -> int:
        """An accepted loop between keyframes ``query`` and ``match``: associate the query's
        features with the match's (by the loop's verified ``T_match_query``) and with the
        ``neighbours`` keyframes either side of the match (through the match's pose in
        ``poses``), merging the two visits' landmarks. Returns the feature pairs associated."""
        for k in (query, match):
            if k not in self.keyframes:
                raise LandmarkError(f"loop keyframe {k} is not in the landmark map")
        q = self.keyframes[query]
        m = self.keyframes[match]
        T_q_m = inv_T(np.asarray(T_match_query, float))
        pairs = [(m, T_q_m)]
        if poses is not None and neighbours > 0:
            ids = sorted(k for k in self.keyframes if k != query)
            pos = ids.index(match)
            T_w_q = poses[match] @ np.asarray(T_match_query, float)
            for k in ids[max(pos - neighbours, 0) : pos] + ids[pos + 1 : pos + 1 + neighbours]:
                if abs(k - query) > neighbours and k in poses:  # not the query's own neighbours
                    pairs.append((self.keyframes[k], inv_T(T_w_q) @ poses[k]))
        before = self.loop_merges
        self._associate(q, pairs, loop=True)
        return self.loop_merges - before

    def _associate(
        self, kf: Keyframe, pairs: list[tuple[Keyframe, np.ndarray]], loop: bool = False
    ) -> int:
        """Guided matching of ``kf`` (a) against each (keyframe b, T_a_b) and the landmark
        bookkeeping: a feature of a takes the landmark of its best-matching b feature (or
        keeps its own), other landmarks it matched are merged into that one, and matched b
        features without a landmark join it (or start a new one with a)."""
        if len(kf.features) < 2:
            return 0
        use_a = self.usable[kf.id]
        tree = cKDTree(kf.features.pixels[use_a])
        K = self.K(kf)
        ia_l, ib_l, nb_l, d_l, lb_l = [], [], [], [], []
        assoc_b = [self.assoc[o.id] for o, _ in pairs]
        for j, (other, T_a_b) in enumerate(pairs):
            m = guided_match(kf, other, T_a_b, K, self.cfg, use_a, self.usable[other.id], tree)
            ia_l.append(m.ia)
            ib_l.append(m.ib)
            nb_l.append(np.full(len(m), j))
            d_l.append(m.distance)
            lb_l.append(assoc_b[j][m.ib])
        ia = np.concatenate(ia_l)
        if not len(ia):
            return int(np.count_nonzero(self.assoc[kf.id] >= 0))
        ib, nb, dist = np.concatenate(ib_l), np.concatenate(nb_l), np.concatenate(d_l)
        lb = self.root(np.concatenate(lb_l))
        # best matches first (distance, then nearer neighbours)
        o = np.lexsort((nb, dist))
        ia, ib, nb, dist, lb = ia[o], ib[o], nb[o], dist[o], lb[o]
        la = self.root(self.assoc[kf.id])  # a's current landmarks (a loop query has some)
        # 1. each feature of a without a landmark takes its best match's landmark; a landmark
        #    goes to one feature of a only (the best match), and not to one a already observes
        chosen = la.copy()
        has = lb >= 0
        cand_ia, cand_l = ia[has], lb[has]
        first = _first_occurrence(cand_ia)
        cand_ia, cand_l = cand_ia[first], cand_l[first]
        free = chosen[cand_ia] < 0
        cand_ia, cand_l = cand_ia[free], cand_l[free]
        taken = np.isin(cand_l, chosen[chosen >= 0])
        cand_ia, cand_l = cand_ia[~taken], cand_l[~taken]
        uniq = _first_occurrence(cand_l)
        chosen[cand_ia[uniq]] = cand_l[uniq]
        # 2. other landmarks matched to a feature of a are the same point: merge them, unless
        #    a keyframe observes both (on two features: they are two points, or one of the
        #    matches is wrong)
        other = has & (chosen[ia] >= 0) & (lb != chosen[ia])
        other_l, into = lb[other], chosen[ia[other]]
        keep = ~np.isin(other_l, chosen[chosen >= 0])
        other_l, into = other_l[keep], into[keep]
        u = _first_occurrence(other_l)  # each merged into one landmark of a only
        other_l, into = other_l[u], into[u]
        ok = ~_coobserved(self.assoc, self.ids, other_l, into)
        merged = self.ids.union(other_l[ok], into[ok])
        self.merges += merged
        if merged:
            chosen = self.root(chosen)
        # 3. matched b features without a landmark: join a's feature's landmark, or a new one
        lone = lb < 0
        need_new = np.unique(ia[lone & (chosen[ia] < 0)])
        if len(need_new):
            chosen[need_new] = self.ids.new(len(need_new))
        for j, (other_kf, _) in enumerate(pairs):
            sel = lone & (nb == j)
            if not sel.any():
                continue
            lm = chosen[ia[sel]]
            seen = np.isin(lm, self.root(assoc_b[j]))  # b already observes it elsewhere
            ibs, lm = ib[sel][~seen], lm[~seen]
            u = _first_occurrence(lm)
            self.assoc[other_kf.id][ibs[u]] = lm[u]
        if loop:
            self.loop_merges += len(np.unique(ia))
        self.assoc[kf.id] = chosen
        return int(np.count_nonzero(chosen >= 0))

    def detach(self, kf_ids: np.ndarray, features: np.ndarray) -> None:
        """Remove observations (outliers after bundle adjustment): feature ``features[k]`` of
        keyframe ``kf_ids[k]`` no longer observes its landmark."""
        kf_ids = np.asarray(kf_ids)
        features = np.asarray(features)
        for k in np.unique(kf_ids):
            self.assoc[int(k)][features[kf_ids == k]] = -1

    # --- queries
    def observations(
        self, kf_ids: Any = None, min_observations: int = 2
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All observations of landmarks seen by at least ``min_observations`` keyframes
        (counted among ``kf_ids``, default all): arrays (keyframe id, feature index, landmark
        root id), one observation per (keyframe, landmark)."""
        ids = sorted(self.keyframes) if kf_ids is None else sorted(int(k) for k in kf_ids)
        kf_l, feat_l, lm_l = [], [], []
        for k in ids:
            a = self.assoc[k]
            f = np.flatnonzero(a >= 0)
            kf_l.append(np.full(len(f), k, np.int64))
            feat_l.append(f)
            lm_l.append(a[f])
        if not kf_l:
            z = np.zeros(0, np.int64)
            return z, z.copy(), z.copy()
        kf = np.concatenate(kf_l)
        feat = np.concatenate(feat_l)
        lm = self.root(np.concatenate(lm_l))
        # one observation per (keyframe, landmark): the first
        key = lm * (max(ids) + 1) + kf
        _, first = np.unique(key, return_index=True)
        first.sort()
        kf, feat, lm = kf[first], feat[first], lm[first]
        _, inv, counts = np.unique(lm, return_inverse=True, return_counts=True)
        keep = counts[inv] >= min_observations
        return kf[keep], feat[keep], lm[keep]

    def track_lengths(self) -> np.ndarray:
        """Keyframes observing each landmark (landmarks seen at least twice)."""
        _, _, lm = self.observations()
        return np.unique(lm, return_counts=True)[1]

    def stats(self) -> dict[str, Any]:
        lengths = self.track_lengths()
        return {
            "keyframes": len(self.keyframes),
            "landmarks": int(len(lengths)),
            "observations": int(lengths.sum()),
            "track_length_mean": round(float(lengths.mean()), 3) if len(lengths) else 0.0,
            "track_length_max": int(lengths.max()) if len(lengths) else 0,
            "merges": self.merges,
            "loop_merges": self.loop_merges,
        }

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Plain data: the associations per keyframe id and the union-find parents; the
        keyframes themselves are saved by the caller and named here by id."""
        return {
            "downsample": self.downsample,
            "keyframes": sorted(self.keyframes),
            "assoc": {int(k): v.copy() for k, v in self.assoc.items()},
            "parent": self.ids.parent.copy(),
            "merges": self.merges,
            "loop_merges": self.loop_merges,
        }

    @classmethod
    def from_state_dict(
        cls, cfg: BAConfig, state: dict[str, Any], keyframes: Mapping[int, Keyframe]
    ) -> LandmarkMap:
        out = cls(cfg, int(state["downsample"]))
        missing = [k for k in state["keyframes"] if k not in keyframes]
        if missing:
            raise LandmarkError(f"landmark state names keyframes {missing[:5]} not given")
        for k in state["keyframes"]:
            out._register(keyframes[k], np.asarray(state["assoc"][k]).copy())
        out.ids.parent = np.asarray(state["parent"], np.int64).copy()
        out.merges = int(state["merges"])
        out.loop_merges = int(state["loop_merges"])
        return out


def _coobserved(
    assoc: Mapping[int, np.ndarray], ids: IdForest, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Per pair: whether some keyframe observes both landmarks ``x[k]`` and ``y[k]``
    (``assoc``: landmark id per feature of each keyframe, by keyframe id)."""
    out = np.zeros(len(x), bool)
    if not len(x):
        return out
    cand = np.unique(np.concatenate([x, y]))
    kf_l, lm_l = [], []
    for k, a in assoc.items():
        r = ids.root(a[a >= 0])
        r = r[np.isin(r, cand)]
        kf_l.append(np.full(len(r), k, np.int64))
        lm_l.append(r)
    kfs, lms = np.concatenate(kf_l), np.concatenate(lm_l)
    n = max(assoc) + 1
    keys = np.unique(lms * n + kfs)
    order = np.argsort(lms, kind="stable")
    lms, kfs = lms[order], kfs[order]
    lo = np.searchsorted(lms, x, "left")
    counts = np.searchsorted(lms, x, "right") - lo
    pair = np.repeat(np.arange(len(x)), counts)
    idx = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    idx += np.repeat(lo, counts)
    hit = np.isin(y[pair] * n + kfs[idx], keys)
    out[pair[hit]] = True
    return out


def _first_occurrence(x: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of each value of ``x`` (in order of appearance)."""
    _, first = np.unique(x, return_index=True)
    return np.sort(first)


def _odometry_poses(keyframes: Mapping[int, Keyframe], kf: Keyframe) -> dict[int, np.ndarray]:
    poses = {k: o.T_world_cam for k, o in keyframes.items()}
    poses[kf.id] = kf.T_world_cam
    return poses
