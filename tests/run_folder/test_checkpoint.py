"""Checkpoints are JSON and numeric ``.npz`` arrays: they round-trip the run's state exactly,
refuse objects when written, cannot run code when loaded (whatever is put in the folder), say
clearly when they are of another format, and name submap files relative to the run folder."""

from __future__ import annotations

import json
import math
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import slam
import slam.api
from slam.cli import app
from slam.config import BackendConfig, LoopConfig, config_from_dict
from slam.keyframe import FeatureSet, Keyframe
from slam.loops.closer import LoopCloser
from slam.loops.place_recognition import KeyframeDatabase
from slam.loops.segments import PendingJoin
from slam.loops.verification import Verification
from slam.run_folder import checkpoint as ck
from slam.run_folder import submaps_dir
from slam.run_folder.checkpoint import (
    FORMAT_VERSION,
    CheckpointError,
    has_checkpoint,
    read_checkpoint,
    write_checkpoint,
)


# --- helpers
def same(a, b, where="state"):
    """Deep equality that also requires equal types (int keys stay int, tuples stay tuples,
    numpy scalars keep their dtype) and equal array dtypes; nan equals nan."""
    assert type(a) is type(b), f"{where}: {type(a)} != {type(b)}"
    if isinstance(a, dict):
        assert list(a) == list(b), f"{where}: keys {list(a)} != {list(b)}"
        for k in a:
            same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), f"{where}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), where
    elif isinstance(a, float | np.floating) and math.isnan(a):
        assert math.isnan(b), where
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"
        if isinstance(a, float) and a == 0:
            assert math.copysign(1, a) == math.copysign(1, b), where


def round_trip(obj, tmp_path: Path):
    """Through the codec and real files: JSON text and an .npz read without pickle."""
    tree, arrays = ck.encode(obj)
    text = json.dumps(tree)
    ck._write_npz(tmp_path / "a.npz", arrays)
    return ck.decode(json.loads(text), ck._read_npz(tmp_path / "a.npz"))


class Boom:
    """Unpickling this creates the file ``marker``: proof that a loader ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def pickled_boom(path: Path, marker: Path) -> None:
    path.write_bytes(pickle.dumps(Boom(marker)))


def npz_with_object_array(path: Path, marker: Path) -> None:
    with open(path, "wb") as f:
        np.savez(f, a0=np.array([Boom(marker), 1], dtype=object))  # pickled inside the .npz


# --- codec
def test_codec_round_trip_keeps_types(tmp_path):
    pcg = np.random.default_rng(7).bit_generator.state  # 128-bit ints
    obj = {
        "rng": pcg,
        "big": [2**200, -(2**130), 0],
        "floats": [math.nan, math.inf, -math.inf, -0.0, 1e-310, 0.1],
        "none": None,
        "flags": [True, False],
        "text": "é \u2603 $t",
        "int_keys": {3: "a", -1: {7: [1, 2]}, 10**30: None},
        "mixed_keys": {1: 1, "1": 2, False: 3, None: 4, (1, "x"): 5, 2.5: 6},
        "tagged": {"$t": "nd", "key": "a0"},  # a plain dict that looks like an encoding
        "tuples": (1, (2.0, "x"), [3, (4,)]),
        "empty": [{}, [], ()],
        "scalars": [
            np.float32(0.1),
            np.float64(math.nan),
            np.float16(1.5),
            np.int8(-3),
            np.uint64(2**64 - 1),
            np.bool_(True),
            np.longdouble(1) / 3,
            np.complex64(1 + 2j),
        ],
        "arrays": [
            np.arange(12, dtype=np.int64).reshape(3, 4),
            np.array([True, False]),
            np.array([np.nan, np.inf, -0.0], np.float32),
            np.zeros((0, 32), np.uint8),
            np.array(5.0),
            np.arange(10.0)[::3],  # not contiguous
            np.asfortranarray(np.ones((2, 3), np.float16)),
            np.array([1 + 1j], np.complex128),
            np.array([1, 2], ">i4"),  # byte order kept
        ],
    }
    back = round_trip(obj, tmp_path)
    same(obj, back)
    # the bit generator continues identically
    rng = np.random.default_rng()
    rng.bit_generator.state = back["rng"]
    assert rng.random() == np.random.default_rng(7).random()


@pytest.mark.parametrize("size", [3, 1000])  # written inline into the JSON, or to the .npz
def test_an_array_met_twice_comes_back_as_one_object(tmp_path, size):
    a, b = np.arange(float(size)), np.arange(float(size))
    back = round_trip({"x": a, "y": [a, b]}, tmp_path)
    assert back["x"] is back["y"][0] and back["y"][1] is not back["x"]
    tree, arrays = ck.encode({"x": a, "y": [a, b]})
    assert len(arrays) == (1 if size == 3 else 2)


_keys = st.one_of(
    st.text(max_size=5), st.integers(), st.booleans(), st.none(), st.floats(allow_nan=False)
)
_leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.builds(
        lambda dt, n, seed: np.random.default_rng(seed).integers(0, 100, n).astype(dt),
        st.sampled_from(["u1", "i2", "i8", "u8", "f2", "f4", "f8", "?", "c16"]),
        st.integers(0, 5),
        st.integers(0, 9),
    ),
)
_plain = st.recursive(
    _leaves,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.lists(inner, max_size=3).map(tuple),
        st.dictionaries(st.text(max_size=5), inner, max_size=4),
        st.dictionaries(_keys, inner, max_size=4),
    ),
    max_leaves=25,
)


@settings(max_examples=60, deadline=None)
@given(_plain)
def test_codec_round_trip_property(tmp_path_factory, obj):
    same(obj, round_trip(obj, tmp_path_factory.mktemp("rt")))


@pytest.mark.parametrize(
    ("obj", "where", "what"),
    [
        ({"a": {3: [1, object()]}}, r"state\.a\[3\]\[1\]", "builtins.object"),
        ({"db": KeyframeDatabase()}, r"state\.db", "KeyframeDatabase"),
        ({"p": [Path("x")]}, r"state\.p\[0\]", "Path"),
        ({"o": np.array([1, "x"], dtype=object)}, r"state\.o", "dtype object"),
        ({"s": np.array(["ab"])}, r"state\.s", "dtype <U2"),
        ({"k": {frozenset(): 1}}, r"state\.k \(key frozenset", "frozenset"),
        ({"d": __import__("collections").deque([1])}, r"state\.d", "deque"),
    ],
)
def test_objects_are_refused_when_written_naming_where(obj, where, what):
    with pytest.raises(CheckpointError, match=where) as exc:
        ck.encode(obj)
    assert what in str(exc.value)


# --- components give plain data
def test_keyframe_database_state_round_trip(tmp_path):
    """Before and after the vocabulary is trained: the restored index has the same state and
    answers every later query as the original."""
    rng = np.random.default_rng(3)
    descs = [rng.integers(0, 256, (150, 32), dtype=np.uint8) for _ in range(14)]
    for cut in (3, 9):
        db = KeyframeDatabase(n_words=64, training_keyframes=4)
        for i, d in enumerate(descs[:cut]):
            db.observe(d)
            db.add(i, d)
        if db.trained:
            db.add(99, np.zeros((0, 32), np.uint8))  # no features: an empty row
        state = db.state_dict()
        back = KeyframeDatabase.from_state_dict(round_trip(state, tmp_path))
        same(state, back.state_dict())
        for i, q in enumerate(descs[cut:], cut):
            for x in (db, back):
                x.observe(q)
                x.add(i, q)
            assert back.query(q, 5) == db.query(q, 5)
        same(db.state_dict(), back.state_dict())
        assert back.trained and len(back) == len(db)
        for r, s in zip(back._rows, db._rows, strict=True):
            assert r.indices.dtype == s.indices.dtype and r.indptr.dtype == s.indptr.dtype
            assert (r != s).nnz == 0


def test_pending_joins_are_plain_data_and_restored(tmp_path):
    kfs = {i: Keyframe(i, float(i), np.eye(4), FeatureSet.empty(), id=i) for i in range(3)}
    closer = LoopCloser(LoopConfig(), BackendConfig())
    ver = Verification(
        True, "ok", 40, 31, 0.775, 0.9, 0.6, np.diag([1.0, 2, 3, 1]), np.eye(6) * 4.5
    )
    closer.segments.pending = [PendingJoin(kfs[0], kfs[2], ver, 5)]
    state = closer.state_dict()
    ck.encode(state)  # plain data
    other = LoopCloser(LoopConfig(), BackendConfig())
    other.load_state_dict(round_trip(state, tmp_path), kfs)
    ((c, k, v, tag),) = [
        (p.candidate, p.query, p.verification, p.record) for p in other.segments.pending
    ]
    assert (c, k, tag) == (kfs[0], kfs[2], 5)
    for name in (
        "accepted",
        "reason",
        "matches",
        "inliers",
        "inlier_ratio",
        "icp_fitness",
        "overlap",
    ):
        assert getattr(v, name) == getattr(ver, name)
    np.testing.assert_array_equal(v.T_candidate_query, ver.T_candidate_query)
    np.testing.assert_array_equal(v.information, ver.information)


# --- real checkpoints
SMALL = {
    "dataset": {"max_frames": 60},
    "tracking": {"downsample": 1},
    "mapping": {"submap_keyframes": 2, "submap_min_frames": 10},
}


class Interrupt(Exception):
    pass


def _interrupted_run(seq: Path, parent: Path, name: str, at: int = 45) -> Path:
    """A run folder started as ``parent/name`` *from* ``parent`` (a relative out path, as a
    user types it), checkpointed every 20 frames and stopped at frame ``at``."""

    def stop(done, total, status):
        if done == at:
            raise Interrupt

    cwd = os.getcwd()
    os.chdir(parent)
    try:
        with pytest.raises(Interrupt):
            slam.api.run_sequence(
                seq, name, config=config_from_dict(SMALL), checkpoint_every=20, progress=stop
            )
    finally:
        os.chdir(cwd)
    return parent / name


@pytest.fixture(scope="module")
def interrupted(synth_loop_320, tmp_path_factory) -> Path:
    """A run folder stopped after its checkpoint at frame 40, with a spilled submap."""
    run = _interrupted_run(synth_loop_320, tmp_path_factory.mktemp("interrupted"), "run")
    header = json.loads((run / "checkpoint" / "state.json").read_text())
    assert header["format"] == "slam-checkpoint" and header["version"] == FORMAT_VERSION
    assert header["position"] == 40
    paths = [sm["path"] for sm in header["state"]["model"]["submaps"] if sm["path"]]
    assert paths and all(p.startswith("submaps/submap_") for p in paths), paths
    return run


@pytest.fixture
def run(interrupted, tmp_path) -> Path:
    """A private copy of the interrupted run folder (under another name)."""
    return Path(shutil.copytree(interrupted, tmp_path / "copy"))


def test_layout_and_exact_round_trip(run, tmp_path):
    folder = run / "checkpoint"
    names = sorted(p.name for p in folder.iterdir())
    assert "state.json" in names and not any(n.endswith(".pkl") or ".tmp" in n for n in names)
    assert any(n.startswith("kf_") for n in names) and any(n.startswith("volume_") for n in names)
    state, position = read_checkpoint(run)
    assert position == 40 and state["checkpoint_every"] == 20
    # written again from the state read: the same state comes back (in another folder too)
    for sm in state["model"]["submaps"]:
        if sm["path"]:
            assert Path(sm["path"]).is_file() and Path(sm["path"]).is_relative_to(run)
    write_checkpoint(run, state, position, 20)
    again, _ = read_checkpoint(run)
    same(state, again)
    # a Slam loaded from it gives back the same state (the volumes' block order aside)
    system = slam.Slam(
        config_from_dict(state["config"]), has_color=True, spill_dir=str(submaps_dir(run))
    )
    system.load_state_dict(state)
    out = system.state_dict()
    for a, b in zip(out["model"]["submaps"], state["model"]["submaps"], strict=True):
        assert (a["volume"] is None) == (b["volume"] is None)
        a["volume"] = b["volume"]
    same({**out, "checkpoint_every": 20}, state)
    # stale files of the previous checkpoint are gone
    header = json.loads((folder / "state.json").read_text())
    assert header["serial"] == 2
    assert sorted(p.name for p in folder.glob("state_*.npz")) == ["state_2.npz"]
    assert all(p.name.endswith("_2.npz") for p in folder.glob("volume_*.npz"))


def test_writing_an_object_changes_nothing(run):
    state, position = read_checkpoint(run)
    before = sorted(p.name for p in (run / "checkpoint").iterdir())
    state["closer"]["records"].append({"x": object()})
    with pytest.raises(CheckpointError, match=r"state\.closer\.records\[\d+\]\.x"):
        write_checkpoint(run, state, position + 1, 20)
    assert sorted(p.name for p in (run / "checkpoint").iterdir()) == before
    assert read_checkpoint(run)[1] == position


def test_a_write_killed_midway_leaves_the_previous_checkpoint(run, monkeypatch):
    state, position = read_checkpoint(run)
    real = ck._write_npz
    calls = []

    def dies(path, arrays):
        calls.append(path.name)
        if path.name.startswith("state_"):
            raise KeyboardInterrupt  # killed before the state document is replaced
        real(path, arrays)

    monkeypatch.setattr(ck, "_write_npz", dies)
    with pytest.raises(KeyboardInterrupt):
        write_checkpoint(run, state, position + 5, 20)
    monkeypatch.undo()
    again, pos = read_checkpoint(run)
    assert pos == position
    same(state, again)


def _doctor(run: Path, edit) -> None:
    """Edit state.json and write its digest again, as a forger would: what the reader checks
    behind the digest."""
    path = run / "checkpoint" / "state.json"
    header = json.loads(path.read_text())
    edit(header)
    header["digest"] = ck._header_digest(header)
    path.write_text(json.dumps(header))


def _inline(**change):
    return {"$t": "nd", "dtype": "<f8", "shape": [2], "data": [1.0, 2.0], **change}


def _first_volume(h):
    return next(sm for sm in h["state"]["model"]["submaps"] if sm["volume"])


def _first_spilled(h):
    return next(sm for sm in h["state"]["model"]["submaps"] if sm["path"])


@pytest.mark.parametrize(
    "how",
    [
        "object array in the state arrays",
        "pickle as the state arrays",
        "pickle as a keyframe",
        "object array in a keyframe",
        "pickle as a volume",
        "pickle as state.json",
        "pickle at the old state.pkl name",
        "pickle as a .npy volume",
        "state arrays named elsewhere",
        "submap path pointing at a pickle outside",
    ],
)
def test_a_doctored_checkpoint_cannot_run_code(run, tmp_path, how):
    folder = run / "checkpoint"
    marker = tmp_path / "ran-code"
    header = json.loads((folder / "state.json").read_text())
    arrays = folder / header["arrays"]
    kf = folder / header["state"]["keyframes"][0]
    volume = folder / _first_volume(header)["volume"]
    if how == "object array in the state arrays":
        npz_with_object_array(arrays, marker)
    elif how == "pickle as the state arrays":
        pickled_boom(arrays, marker)
    elif how == "pickle as a keyframe":
        pickled_boom(kf, marker)
    elif how == "object array in a keyframe":
        npz_with_object_array(kf, marker)
    elif how == "pickle as a volume":
        pickled_boom(volume, marker)
    elif how == "pickle as state.json":
        pickled_boom(folder / "state.json", marker)
    elif how == "pickle at the old state.pkl name":
        (folder / "state.json").unlink()
        pickled_boom(folder / "state.pkl", marker)
    elif how == "pickle as a .npy volume":
        np.save(volume.with_suffix(".npy"), np.array([Boom(marker)], dtype=object))
        volume.with_suffix(".npy").rename(volume)
    elif how == "state arrays named elsewhere":
        npz_with_object_array(tmp_path / "evil.npz", marker)
        _doctor(run, lambda h: h.update(arrays="../../evil.npz"))
    elif how == "submap path pointing at a pickle outside":
        pickled_boom(tmp_path / "evil.npz", marker)
        _doctor(run, lambda h: _first_spilled(h).update(path=str(tmp_path / "evil.npz")))
    with pytest.raises(slam.SlamError) as exc:
        state, _ = read_checkpoint(run)
        slam.Slam(config_from_dict(SMALL), spill_dir=str(submaps_dir(run))).load_state_dict(state)
    msg = str(exc.value)
    assert "--overwrite" in msg, msg
    assert not marker.exists()
    # the doctoring was live: a pickle-enabled loader would have run the code
    if how.startswith(("pickle", "object")):
        target = {
            "object array in the state arrays": arrays,
            "pickle as the state arrays": arrays,
            "pickle as a keyframe": kf,
            "object array in a keyframe": kf,
            "pickle as a volume": volume,
            "pickle as state.json": folder / "state.json",
            "pickle at the old state.pkl name": folder / "state.pkl",
            "pickle as a .npy volume": volume,
        }[how]
        loaded = np.load(target, allow_pickle=True)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            loaded["a0"]
        assert marker.exists()


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda h: h.update(format="something-else"), "format 'something-else'"),
        (lambda h: h.pop("format"), "format None"),
        (lambda h: h.update(version=0), "format version 0"),
        (lambda h: h.update(version=FORMAT_VERSION + 1), f"format version {FORMAT_VERSION + 1}"),
        (lambda h: h["state"].update(tracker={"$t": "nd", "key": "a999999"}), "a999999"),
        (lambda h: h["state"].update(tracker={"$t": "pickle", "data": "x"}), "'pickle'"),
        (lambda h: h["state"].update(x={"$t": "np", "dtype": "O", "value": 1}), "'O'"),
        (lambda h: h["state"].update(x={"$t": "np", "dtype": "<i8", "value": "1"}), "'1'"),
        (lambda h: h["state"].update(x={"$t": "nd", "key": ["a0"]}), "not a string"),
        (lambda h: h["state"].update(x={"$t": "dict", "items": [[[1], 2]]}), "unhashable"),
        (lambda h: h["state"].update(x={"$t": "dict", "items": [1]}), "pair"),
        (lambda h: h["state"].update(x={"$t": "tuple", "items": {}}), "JSON list"),
        (lambda h: h["state"].update(x={"$t": "nd", "key": "a0", "extra": 1}), "extra"),
        (lambda h: h["state"].update(x=_inline(data=["1", "2"])), "inline array data"),
        (lambda h: h["state"].update(x=_inline(data=[[1.0], [2.0]])), "inline array data"),
        (lambda h: h["state"].update(x=_inline(shape=[3])), "cannot reshape"),
        (lambda h: h["state"].update(x=_inline(shape=[-2, -1])), "array shape"),
        (lambda h: h["state"].update(x=_inline(dtype="V8")), "'V8'"),
        (lambda h: h["state"]["keyframes"].append("kf_../../x.npz"), "not a checkpoint file"),
        (lambda h: h["state"]["keyframes"].append("kf_999999.npz"), "kf_999999.npz"),
        (lambda h: _first_volume(h).update(volume="/etc/passwd"), "not a checkpoint file"),
        (lambda h: _first_spilled(h).update(path="../../x.npz"), "leaves the run folder"),
        (lambda h: _first_spilled(h).update(path="/etc/passwd"), "leaves the run folder"),
        (lambda h: _first_spilled(h).update(path="submaps/nope.npz"), "is missing"),
        (lambda h: _first_spilled(h).update(path=7), "not a non-empty string"),
        (lambda h: h.update(position="forty"), "forty"),
        (lambda h: h.pop("state"), "'state'"),
        (lambda h: h.update(state=[]), "damaged"),
    ],
)
def test_an_edited_state_document_is_a_clear_error(run, edit, says):
    _doctor(run, edit)
    with pytest.raises(CheckpointError) as exc:
        read_checkpoint(run)
    msg = str(exc.value)
    assert says in msg and "--overwrite" in msg, msg
    assert isinstance(exc.value, slam.RunFolderError)


@pytest.mark.parametrize("text", ["", "{", "[1, 2]", '"slam"', "NaN", "\x00\xff"])
def test_a_state_document_that_is_not_ours(run, text):
    (run / "checkpoint" / "state.json").write_bytes(text.encode("latin-1"))
    with pytest.raises(CheckpointError, match="not a checkpoint of this package.*--overwrite"):
        read_checkpoint(run)


def test_an_old_format_checkpoint_says_so(synth_loop_320, tmp_path):
    """Today's layout before the format had a version: state.pkl and kf_NNNNNN.pkl."""
    run = tmp_path / "old"
    (run / "checkpoint").mkdir(parents=True)
    marker = tmp_path / "ran-code"
    pickled_boom(run / "checkpoint" / "state.pkl", marker)
    pickled_boom(run / "checkpoint" / "kf_000000.pkl", marker)
    (run / "config.yaml").write_text(f"dataset: {{path: '{synth_loop_320}'}}\n")
    assert has_checkpoint(run)
    with pytest.raises(CheckpointError, match=r"state\.pkl: a checkpoint in the old pickle format"):
        read_checkpoint(run)
    res = CliRunner().invoke(app, ["run", "--resume", str(run)])
    assert res.exit_code == 2, res.output
    flat = " ".join(res.output.split())
    assert "old pickle format" in flat and "--overwrite" in flat, flat
    assert not marker.exists()


def test_no_checkpoint_at_all(tmp_path):
    assert not has_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="no checkpoint to resume from"):
        read_checkpoint(tmp_path)


def test_a_submap_outside_the_run_folder_is_refused_when_written(run, tmp_path):
    state, position = read_checkpoint(run)
    sm = next(sm for sm in state["model"]["submaps"] if sm["path"])
    sm["path"] = str(tmp_path / "elsewhere.npz")
    with pytest.raises(CheckpointError, match=r"state\.model\.submaps\[\d+\]\.path.*not inside"):
        write_checkpoint(run, state, position, 20)


def test_resume_from_another_directory_gives_the_same_run(interrupted, tmp_path, monkeypatch):
    """The run was started as ``run`` from its parent; resumed from the parent and from an
    unrelated directory (holding a decoy submap at the old cwd-relative path, which the old
    format would have fused), both finish identically."""
    from slam.api import resume_run

    shutil.copytree(interrupted, tmp_path / "a")
    b = Path(shutil.copytree(interrupted, tmp_path / "b"))
    elsewhere = tmp_path / "elsewhere"
    decoy = elsewhere / "run" / "submaps"
    decoy.mkdir(parents=True)
    for p in (interrupted / "submaps").iterdir():
        np.savez(decoy / p.name, tsdf=np.zeros(3))
    monkeypatch.chdir(tmp_path)
    res_a, _ = resume_run("a")
    monkeypatch.chdir(elsewhere)
    res_b, _ = resume_run(os.path.relpath(b, elsewhere))
    ma, mb = res_a.metrics, res_b.metrics
    assert ma["resumed_at_frame"] == mb["resumed_at_frame"] == 40
    assert ma["frames"] == mb["frames"] == 60
    for key in ("frames_tracked", "keyframes", "submaps", "loops_accepted"):
        assert ma[key] == mb[key], key
    diff = np.abs(res_a.trajectory.poses - res_b.trajectory.poses).max()
    # ICP's parallel sums are not bit-reproducible: 0.02-0.04 mm measured over 5 resumes (up to
    # 3 mm before ray-casts kept every block in their range map: see slam/mapping/range_map.py)
    assert diff < 0.0005, diff
    assert abs(ma["ate_rmse_m"] - mb["ate_rmse_m"]) < 0.001


@pytest.mark.parametrize("position", [1_000_000_000, -5, 0, 39, 41])
def test_a_position_the_state_does_not_hold_is_refused(run, position):
    """The header's frame position must be what the state holds (40 frames of 60): a run
    resumed from 1e9 or -5 'completed' with frames never processed, without a word."""
    from slam.api import resume_run

    _doctor(run, lambda h: h.update(position=position))
    with pytest.raises(slam.RunFolderError, match=f"position says {position} frames.*--overwrite"):
        resume_run(run)


def test_a_spilled_submap_that_is_a_pickle_or_a_link_outside_is_refused(run, tmp_path):
    """`--resume` ended in a numpy traceback from TSDFVolume.load mid-run when a spilled
    submap was replaced by a pickle, and read an outside folder when submaps/ was a link."""
    import pickle

    header = json.loads((run / "checkpoint" / "state.json").read_text())
    spilled = [sm["path"] for sm in header["state"]["model"]["submaps"] if sm["path"]]
    target = run / spilled[0]
    target.write_bytes(pickle.dumps({"keys": [1, 2, 3]}))
    with pytest.raises(CheckpointError, match=rf"{target.name}: damaged checkpoint"):
        read_checkpoint(run)
    outside = Path(shutil.copytree(run / "submaps", tmp_path / "outside"))
    shutil.rmtree(run / "submaps")
    (run / "submaps").symlink_to(outside, target_is_directory=True)
    with pytest.raises(CheckpointError, match="link that leaves the run folder"):
        read_checkpoint(run)


def test_a_checkpoint_folder_or_keyframe_linked_outside_is_refused(run, tmp_path):
    """checkpoint/ linked to an outside folder had new checkpoint files written there; a
    keyframe file linked outside was read."""
    ckpt = run / "checkpoint"
    kf = next(ckpt.glob("kf_*.npz"))
    outside = tmp_path / "outside.npz"
    shutil.copy(kf, outside)
    kf.unlink()
    kf.symlink_to(outside)
    with pytest.raises(CheckpointError, match="a keyframe file is a link that leaves"):
        read_checkpoint(run)
    moved = Path(shutil.copytree(ckpt, tmp_path / "elsewhere", symlinks=True))
    shutil.rmtree(ckpt)
    ckpt.symlink_to(moved, target_is_directory=True)
    with pytest.raises(CheckpointError, match="the checkpoint folder is a link that leaves"):
        read_checkpoint(run)
    from slam.run_folder.checkpoint import write_checkpoint

    with pytest.raises(CheckpointError, match="the checkpoint folder is a link that leaves"):
        write_checkpoint(run, {"keyframes": [], "model": {"submaps": []}}, 0)
