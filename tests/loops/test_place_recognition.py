"""Bag-of-binary-words retrieval: the keyframe that shares most descriptors ranks first."""

import numpy as np

from slam.loops.place_recognition import KeyframeDatabase, kmajority


def noisy_copy(desc, rng, bits=20):
    """The same descriptors with ``bits`` random bits flipped each (a re-detection)."""
    out = np.unpackbits(desc, axis=1)
    for row in out:
        row[rng.choice(256, bits, replace=False)] ^= 1
    return np.packbits(out, axis=1)


def test_kmajority_recovers_clusters():
    rng = np.random.default_rng(0)
    centres = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    desc = np.vstack([noisy_copy(np.repeat(c[None], 40, 0), rng, 10) for c in centres])
    words = kmajority(desc, 5, iterations=8, rng=rng)
    dist = np.unpackbits(words[:, None] ^ centres[None], axis=2).sum(-1)
    assert np.all(dist.min(axis=0) <= 3)  # every true centre has a word within 3 bits


def test_query_ranks_the_revisited_keyframe_first():
    rng = np.random.default_rng(1)
    # a "scene" of 3000 distinct local features; each keyframe sees 400 of them
    scene = rng.integers(0, 256, (3000, 32), dtype=np.uint8)
    db = KeyframeDatabase(n_words=300, training_keyframes=5)
    views = []
    for k in range(30):
        idx = rng.choice(3000, 400, replace=False)
        views.append(idx)
        desc = noisy_copy(scene[idx], rng)
        db.observe(desc)
        db.add(k, desc)
    assert db.trained and len(db) == 30
    for target in range(30):
        q = noisy_copy(scene[views[target]], rng)
        ranked = db.query(q, top_k=3)
        assert ranked[0][0] == target, ranked


def test_untrained_database_returns_nothing():
    db = KeyframeDatabase(training_keyframes=5)
    db.observe(np.zeros((10, 32), np.uint8))
    db.add(0, np.zeros((10, 32), np.uint8))
    assert db.query(np.zeros((10, 32), np.uint8)) == []
