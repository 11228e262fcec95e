"""Revisit (loop candidate) retrieval: a bag of binary words built online over keyframe ORB
descriptors, with an inverted index and tf-idf scoring (as DBoW2 in ORB-SLAM, flat vocabulary).

The vocabulary is learnt from the first keyframes of the run itself (k-majority clustering of
their binary descriptors), so nothing has to be shipped or downloaded. A query touches only the
index columns of the words it contains (a sparse column slice), not every stored keyframe.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.sparse as sp

log = logging.getLogger(__name__)


def _nearest_words(descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Index of the nearest word (Hamming) of each descriptor."""
    matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(descriptors, words)
    labels = np.empty(len(descriptors), dtype=np.int64)
    labels[[m.queryIdx for m in matches]] = [m.trainIdx for m in matches]
    return labels


def _kmeanspp(desc: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding with Hamming distance: indices of ``k`` well-spread descriptors."""
    words = np.ascontiguousarray(desc).view(np.uint64)  # 4 x 64 bits: fast popcounts

    def sq_dist(i: int) -> np.ndarray:
        return np.bitwise_count(words ^ words[i]).sum(axis=1).astype(np.float64) ** 2

    chosen = [int(rng.integers(len(desc)))]
    d2 = sq_dist(chosen[0])
    for _ in range(1, k):
        total = d2.sum()
        i = int(np.searchsorted(np.cumsum(d2), rng.random() * total)) if total > 0 else 0
        i = min(i, len(desc) - 1)
        chosen.append(i)
        d2 = np.minimum(d2, sq_dist(i))
    return np.array(chosen)


def kmajority(
    descriptors: np.ndarray,
    n_words: int,
    iterations: int = 5,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """k-majority clustering of binary descriptors (k-means with Hamming distance and bitwise
    majority centres). Returns (n_words, 32) uint8 words (fewer if there are fewer descriptors)."""
    rng = rng or np.random.default_rng(0)
    desc = np.unique(descriptors, axis=0)
    k = min(n_words, len(desc))
    # k-means++ seeds from a random sample of 3k descriptors: its cost is k passes over the pool
    # (0.34 s for 1000 words over 10000 descriptors, 0.1 s over 3000); the k-majority
    # iterations below then use every descriptor
    pool = desc if len(desc) <= 3 * k else desc[rng.choice(len(desc), 3 * k, replace=False)]
    words = pool[_kmeanspp(pool, k, rng)].copy()
    bits = np.unpackbits(desc, axis=1).astype(np.float32)  # (N, 256)
    for _ in range(iterations):
        labels = _nearest_words(desc, words)
        onehot = sp.csr_matrix(
            (np.ones(len(desc), np.float32), (labels, np.arange(len(desc)))), shape=(k, len(desc))
        )
        counts = np.asarray(onehot.sum(axis=1)).ravel()
        sums = onehot @ bits
        used = counts > 0  # an empty cluster keeps its centre
        words[used] = np.packbits(sums[used] * 2 > counts[used, None], axis=1)
    return words


@dataclass
class KeyframeDatabase:
    """Bag-of-binary-words index of keyframes: ``add`` keyframes, ``query`` the most similar.

    The vocabulary is trained on the descriptors of the first ``training_keyframes`` keyframes
    passed to :meth:`observe` (every new keyframe, whether or not it is indexed yet); keyframes
    added before that are indexed as soon as it exists.
    """

    n_words: int = 1000
    training_keyframes: int = 10
    seed: int = 0
    words: np.ndarray | None = None
    _pending: list[tuple[int, np.ndarray]] = field(default_factory=list)
    _training: list[np.ndarray] = field(default_factory=list)
    _ids: list[int] = field(default_factory=list)
    _rows: list[sp.csr_matrix] = field(default_factory=list)  # term frequencies, L1-normalised
    _doc_freq: np.ndarray | None = None
    _matrix: sp.csc_matrix | None = None  # stacked rows, rebuilt lazily (column access)

    def __len__(self) -> int:
        return len(self._ids) + len(self._pending)

    @property
    def trained(self) -> bool:
        return self.words is not None

    def observe(self, descriptors: np.ndarray) -> None:
        """Offer a new keyframe's descriptors for vocabulary training (until trained)."""
        if self.trained or len(descriptors) == 0:
            return
        self._training.append(descriptors)
        if len(self._training) >= self.training_keyframes:
            self._train()

    def add(self, kf_id: int, descriptors: np.ndarray) -> None:
        """Index a keyframe's ORB descriptors (N, 32) uint8."""
        if not self.trained:
            self._pending.append((kf_id, descriptors))
            return
        self._insert(kf_id, descriptors)

    def _train(self) -> None:
        pool = self._training
        self.words = kmajority(np.vstack(pool), self.n_words, rng=np.random.default_rng(self.seed))
        self._doc_freq = np.zeros(len(self.words))
        log.info(
            "place recognition: trained a %d-word vocabulary on %d descriptors of %d keyframes",
            len(self.words),
            sum(len(d) for d in pool),
            len(pool),
        )
        self._training = []
        pending, self._pending = self._pending, []
        for kf_id, desc in pending:
            self._insert(kf_id, desc)

    def _bow(self, descriptors: np.ndarray) -> sp.csr_matrix:
        assert self.words is not None
        n = len(self.words)
        if len(descriptors) == 0:
            return sp.csr_matrix((1, n), dtype=np.float64)
        counts = np.bincount(_nearest_words(descriptors, self.words), minlength=n).astype(float)
        return sp.csr_matrix(counts / counts.sum())

    def _insert(self, kf_id: int, descriptors: np.ndarray) -> None:
        row = self._bow(descriptors)
        assert self._doc_freq is not None
        self._doc_freq[row.indices] += 1
        self._ids.append(kf_id)
        self._rows.append(row)
        self._matrix = None

    def query(
        self, descriptors: np.ndarray, top_k: int = 3, min_score: float = 0.0
    ) -> list[tuple[int, float]]:
        """The ``top_k`` indexed keyframes most similar to ``descriptors``: (kf_id, score) with
        score = sum over words of min(q_w, d_w), q and d tf-idf vectors normalised to sum 1
        (= 1 - |q - d|_1 / 2, DBoW2's L1 score), best first."""
        if not self.trained or not self._ids or len(descriptors) == 0:
            return []
        if self._matrix is None:
            self._matrix = sp.vstack(self._rows, format="csc")
        assert self._doc_freq is not None
        idf = np.log(len(self._ids) / np.maximum(self._doc_freq, 1.0))
        q = self._bow(descriptors)
        words = q.indices
        qv = q.data * idf[words]
        if qv.sum() <= 0:
            return []
        qv /= qv.sum()
        sub = self._matrix[:, words].toarray() * idf[words]  # only the query's words
        norms = np.asarray(self._matrix @ idf).ravel()  # each keyframe's tf-idf L1 norm
        scores = np.minimum(sub / np.maximum(norms, 1e-12)[:, None], qv).sum(axis=1)
        order = np.argsort(-scores)[:top_k]
        return [(self._ids[i], float(scores[i])) for i in order if scores[i] >= min_score]

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Plain data and arrays (a snapshot: adding keyframes later does not change it). The
        keyframes' bag-of-words rows are stored stacked as one CSR matrix (``row_ptr``,
        ``row_words``, ``row_weights``); the column-access cache is rebuilt when needed."""
        rows = self._rows
        ptr = np.zeros(len(rows) + 1, np.int64)
        ptr[1:] = np.cumsum([r.nnz for r in rows], dtype=np.int64)
        return {
            "n_words": self.n_words,
            "training_keyframes": self.training_keyframes,
            "seed": self.seed,
            "words": None if self.words is None else self.words.copy(),
            "pending_ids": [kf_id for kf_id, _ in self._pending],
            "pending_descriptors": [d.copy() for _, d in self._pending],
            "training": [d.copy() for d in self._training],
            "ids": list(self._ids),
            "row_ptr": ptr,
            "row_words": np.concatenate([r.indices for r in rows] or [np.zeros(0, np.int32)]),
            "row_weights": np.concatenate([r.data for r in rows] or [np.zeros(0)]),
            "doc_freq": None if self._doc_freq is None else self._doc_freq.copy(),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> KeyframeDatabase:
        """The database :meth:`state_dict` was taken from."""
        db = cls(int(state["n_words"]), int(state["training_keyframes"]), int(state["seed"]))
        words = state["words"]
        db.words = None if words is None else np.array(words, np.uint8)
        db._pending = [
            (int(k), np.asarray(d))
            for k, d in zip(state["pending_ids"], state["pending_descriptors"], strict=True)
        ]
        db._training = [np.asarray(d) for d in state["training"]]
        db._ids = [int(k) for k in state["ids"]]
        n = 0 if db.words is None else len(db.words)
        ptr = np.asarray(state["row_ptr"], np.int64)
        words_idx, weights = np.asarray(state["row_words"]), np.asarray(state["row_weights"])
        if len(ptr) != len(db._ids) + 1:
            raise ValueError(f"{len(ptr) - 1} bag-of-words rows for {len(db._ids)} keyframes")
        db._rows = [
            sp.csr_matrix(
                (weights[a:b].copy(), words_idx[a:b].copy(), np.array([0, b - a])), shape=(1, n)
            )
            for a, b in zip(ptr[:-1], ptr[1:], strict=True)
        ]
        doc_freq = state["doc_freq"]
        db._doc_freq = None if doc_freq is None else np.array(doc_freq, np.float64)
        db._matrix = None
        return db
