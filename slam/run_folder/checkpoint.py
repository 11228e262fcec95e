"""Checkpoints of a run: the :class:`~slam.system.Slam` state in ``RUN_DIR/checkpoint/``, in a
format that cannot run code when it is loaded (JSON and ``.npz`` arrays read with
``allow_pickle=False``; no pickle: a checkpoint folder from someone else is data, not a program).

Layout (format ``slam-checkpoint``, version :data:`FORMAT_VERSION`):

- ``state.json``: the format name and version, the position in the frame list, the checkpoint
  serial K and interval, the names of the files below and the state itself as one JSON document,
  in which each numpy array is a reference into ``state_K.npz`` (arrays of at most 16 elements,
  such as poses, are written inline, exactly);
- ``state_K.npz``: the arrays of ``state.json``;
- ``kf_NNNNNN.npz``: one keyframe (ORB features and depth), its JSON document in the entry
  ``__doc__`` and its arrays beside it; written once (keyframes never change), except that a
  file the current ``state.json`` does not name (left by a killed write) is written again;
- ``volume_SSSS_K.npz``: the blocks of submap SSSS, held in memory at checkpoint K.

Submaps spilled to ``RUN_DIR/submaps/`` are final once written and only referenced, by their
name relative to the run folder (resolved against the folder being resumed, whatever the
current directory; a name that leaves the folder is refused).

The state goes through :mod:`slam.run_folder.codec` (plain data only: anything else is refused
when the checkpoint is *written*, naming where in the state it sits).

Each file's SHA-256 is in ``state.json`` (``digests``) and ``state.json``'s own, over the rest
of it, in its ``digest``: a checkpoint damaged after it was written (a disk error, a file cut
short, an edit) is refused as a whole when it is read, before any of it is used. (Whoever
rewrites the digests as well can make a checkpoint that loads and ends the run in an error; it
still cannot run code.)

A checkpoint is replaced atomically: new files first (each fsynced, written under a temporary
name and renamed), then ``state.json`` by rename, then files the new state does not name are
removed, so a kill at any moment leaves the previous checkpoint or the new one, whole.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import time
import zipfile
from collections.abc import Mapping
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from slam.files import file_digest as _file_digest
from slam.files import write_via_tmp as _write_via_tmp
from slam.run_folder.codec import _ARRAY_KINDS, CheckpointError, _list, decode, encode
from slam.run_folder.layout import CHECKPOINT_DIR

log = logging.getLogger(__name__)

STATE_FILE = "state.json"
FORMAT_NAME = "slam-checkpoint"
FORMAT_VERSION = 2  # 2: the digests
#: the state file of checkpoints written before the format had a name and version (pickles)
OLD_STATE_FILE = "state.pkl"

_DOC = "__doc__"  # the JSON document inside a keyframe's .npz
_STATE_ARRAYS = re.compile(r"state_\d+\.npz")
_KEYFRAME = re.compile(r"kf_\d{6,}\.npz")
_VOLUME = re.compile(r"volume_\d{4,}_\d+\.npz")
_OURS = (_STATE_ARRAYS, _KEYFRAME, _VOLUME)
_RESTART = "start the run again with `slam run SEQUENCE --out RUN_DIR --overwrite`"


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_bytes(path: Path, data: bytes) -> None:
    _write_via_tmp(path, lambda f: f.write(data))


def _write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    _write_via_tmp(path, lambda f: np.savez(f, allow_pickle=False, **arrays))


def _json(tree: Any) -> bytes:
    return json.dumps(tree, separators=(",", ":")).encode()


def _header_digest(header: Mapping[str, Any]) -> str:
    """The SHA-256 of ``state.json`` without its ``digest`` entry, as :func:`_json` writes it."""
    return hashlib.sha256(_json({k: v for k, v in header.items() if k != "digest"})).hexdigest()


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file, read without pickle; only bool and numeric arrays."""
    z = np.load(path, allow_pickle=False)
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError("not an .npz archive")
    with z:
        out = {k: z[k] for k in z.files}
    for k, a in out.items():
        if a.dtype.kind not in _ARRAY_KINDS:
            raise ValueError(f"array {k!r} has dtype {a.dtype}, not bool or numeric")
    return out


def _check_volume_file(path: Path) -> None:
    """A spilled submap's ``.npz`` (:meth:`~slam.mapping.tsdf.TSDFVolume.save`) by its headers
    alone (the arrays are read when the submap is needed): a zip of ``.npy`` members of bool or
    numeric dtype, ``keys`` among them. Anything else (a pickle, text) raises ValueError."""
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        if "keys.npy" not in names:
            raise ValueError("not a saved TSDF volume (no 'keys' array)")
        for name in names:
            with zf.open(name) as f:
                version = np.lib.format.read_magic(f)
                read = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                _, _, dtype = read(f)
            if dtype.kind not in _ARRAY_KINDS:
                raise ValueError(f"array {name!r} has dtype {dtype}, not bool or numeric")


def _write_document(path: Path, obj: Any, where: str) -> None:
    tree, arrays = encode(obj, where)
    _write_npz(path, {_DOC: np.frombuffer(_json(tree), np.uint8), **arrays})


def _read_document(path: Path) -> Any:
    arrays = _read_npz(path)
    doc = arrays.pop(_DOC, None)
    if doc is None or doc.dtype != np.uint8 or doc.ndim != 1:
        raise ValueError(f"no {_DOC} entry (uint8 JSON text)")
    return decode(json.loads(doc.tobytes().decode()), arrays)


def _run_relative(run_dir: Path, path: Any, where: str) -> str:
    """``path`` (absolute or relative to the current directory) by its name in the run folder."""
    base = run_dir.resolve()
    full = Path(path).resolve()
    try:
        return full.relative_to(base).as_posix()
    except ValueError:
        raise CheckpointError(
            f"cannot checkpoint {where}: submap file {path} is not inside the run folder "
            f"{run_dir}; spilled submaps must live in RUN_DIR/submaps/"
        ) from None


def _in_run(run_dir: Path, name: Any, where: str) -> Path:
    """A file named relative to the run folder, refusing names that leave it."""
    if type(name) is not str or not name:
        raise CheckpointError(f"{where}: file name {name!r} is not a non-empty string; {_RESTART}")
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or "\\" in name or Path(name).is_absolute():
        raise CheckpointError(
            f"{where}: file name {name!r} leaves the run folder {run_dir} (absolute or '..'); "
            f"checkpoints name files inside it only: {_RESTART}"
        )
    return run_dir / p


def _inside(run_dir: Path, path: Path, what: str) -> None:
    """``path`` must stay inside ``run_dir`` once links are followed: a checkpoint neither
    writes nor reads outside its run folder."""
    if not path.resolve().is_relative_to(run_dir.resolve()):
        raise CheckpointError(
            f"{path}: {what} is a link that leaves the run folder {run_dir}; remove the link "
            f"and {_RESTART}"
        )


def _own_name(name: Any, pattern: re.Pattern[str], where: str) -> str:
    if type(name) is not str or not pattern.fullmatch(name):
        raise ValueError(f"{where}: {name!r} is not a checkpoint file name")
    return name


def _read_header(folder: Path) -> dict[str, Any]:
    """``state.json``, checked to be ours and of this version."""
    path = folder / STATE_FILE
    try:
        header = json.loads(path.read_bytes().decode())
    except (OSError, ValueError, RecursionError) as exc:
        raise CheckpointError(
            f"{path}: not a checkpoint of this package (unreadable or not JSON: {exc}); {_RESTART}"
        ) from None
    found = header.get("format") if isinstance(header, dict) else None
    if found != FORMAT_NAME:
        raise CheckpointError(
            f"{path}: not a checkpoint of this package (format {found!r}, expected "
            f"{FORMAT_NAME!r}); {_RESTART}"
        )
    version = header.get("version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {version!r}, this version of the package reads "
            f"version {FORMAT_VERSION} only; {_RESTART}"
        )
    try:
        same = header.get("digest") == _header_digest(header)
    except (TypeError, ValueError, RecursionError):
        same = False
    if not same:
        raise CheckpointError(
            f"{path}: damaged checkpoint (its digest does not match its contents: it changed "
            f"after it was written); {_RESTART}"
        )
    return header


def _verified(folder: Path, header: dict[str, Any], name: str) -> Path:
    """``folder / name`` when its SHA-256 is the one ``state.json`` recorded."""
    path = folder / name
    digests = header.get("digests")
    if not isinstance(digests, dict) or digests.get(name) != _file_digest(path):
        raise CheckpointError(
            f"{path}: damaged checkpoint (the file's SHA-256 is not the one {STATE_FILE} "
            f"recorded: it changed after it was written); {_RESTART}"
        )
    return path


#: what this process last wrote to each checkpoint folder (saves re-reading state.json)
_written: dict[Path, tuple[tuple[int, int, int], int, dict[str, str]]] = {}


def _stat_key(path: Path) -> tuple[int, int, int]:
    st = path.stat()
    return st.st_ino, st.st_size, st.st_mtime_ns


def _previous(folder: Path) -> tuple[int, dict[str, str]]:
    """The serial for the next checkpoint and the keyframe files the current one names, with
    their digests."""
    path = folder / STATE_FILE
    if not path.is_file():
        return 0, {}
    mine = _written.get(folder.resolve())
    if mine is not None and mine[0] == _stat_key(path):
        return mine[1] + 1, mine[2]
    try:
        header = _read_header(folder)
        digests = header["digests"]
        kf = {str(n): str(digests[n]) for n in header["state"]["keyframes"]}
        return int(header["serial"]) + 1, kf
    except (CheckpointError, KeyError, TypeError, ValueError) as exc:
        log.warning("%s: replacing an unreadable checkpoint (%s)", folder, exc)
        return 0, {}


def write_checkpoint(
    run_dir: str | Path, state: dict[str, Any], position: int, every: int = 0
) -> Path:
    """Write ``state`` (from :meth:`Slam.state_dict`) with ``position``, the number of entries
    of the frame list already processed, and ``every``, the checkpoint interval (kept for the
    resumed run). Returns the checkpoint folder. Raises :class:`CheckpointError`, before
    anything is replaced, if the state holds something that is not plain data."""
    t0 = time.perf_counter()
    run_dir = Path(run_dir)
    folder = run_dir / CHECKPOINT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    _inside(run_dir, folder, "the checkpoint folder")
    serial, committed = _previous(folder)

    # encode everything first: a state that is not plain data changes nothing on disk
    keyframes = state["keyframes"]
    kf_files = [f"kf_{int(kf['id']):06d}.npz" for kf in keyframes]
    submaps, volumes = [], {}
    for j, sm in enumerate(state["model"]["submaps"]):
        sm = dict(sm)
        where = f"state.model.submaps[{j}]"
        if sm["volume"] is not None:
            name = f"volume_{int(sm['id']):04d}_{serial}.npz"
            volume = sm["volume"]
            if type(volume) is not dict or any(
                type(k) is not str or type(v) is not np.ndarray for k, v in volume.items()
            ):
                raise CheckpointError(
                    f"cannot checkpoint {where}.volume: not a dict of named numpy arrays"
                )
            encode(volume, f"{where}.volume")  # checks the dtypes
            volumes[name] = volume
            sm["volume"] = name
        if sm.get("path") is not None:
            sm["path"] = _run_relative(run_dir, sm["path"], f"{where}.path")
        submaps.append(sm)
    core = {**state, "keyframes": kf_files, "model": {**state["model"], "submaps": submaps}}
    tree, arrays = encode(core, "state")
    arrays_file = f"state_{serial}.npz"

    # new files (each with its digest), then the state document by rename, then what the new
    # state does not name
    digests = {}
    for i, (kf, name) in enumerate(zip(keyframes, kf_files, strict=True)):
        if name not in committed or not (folder / name).is_file():
            _write_document(folder / name, kf, f"state.keyframes[{i}]")
            digests[name] = _file_digest(folder / name)
        else:
            digests[name] = committed[name]
    for name, volume in volumes.items():
        _write_npz(folder / name, volume)
        digests[name] = _file_digest(folder / name)
    _write_npz(folder / arrays_file, arrays)
    digests[arrays_file] = _file_digest(folder / arrays_file)
    _fsync_dir(folder)
    header = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "serial": serial,
        "position": int(position),
        "checkpoint_every": int(every),
        "arrays": arrays_file,
        "state": tree,
        "digests": digests,
    }
    header["digest"] = _header_digest(header)
    document = _json(header)
    _write_bytes(folder / STATE_FILE, document)
    _fsync_dir(folder)
    kf_digests = {n: digests[n] for n in kf_files}
    _written[folder.resolve()] = (_stat_key(folder / STATE_FILE), serial, kf_digests)
    keep = {arrays_file, *kf_files, *volumes}
    for p in folder.iterdir():
        stale = any(pat.fullmatch(p.name) for pat in _OURS) and p.name not in keep
        if stale or (p.name.startswith(".") and p.name.endswith(".tmp")):
            p.unlink(missing_ok=True)
    log.debug(
        "checkpoint %d at frame position %d written in %.0f ms (%d kB state document)",
        serial,
        position,
        (time.perf_counter() - t0) * 1e3,
        len(document) // 1024,
    )
    return folder


def has_checkpoint(run_dir: str | Path) -> bool:
    """Whether the run folder holds a checkpoint (of any format: :func:`read_checkpoint` says
    whether it can be read)."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    return (folder / STATE_FILE).is_file() or (folder / OLD_STATE_FILE).is_file()


def read_checkpoint(run_dir: str | Path) -> tuple[dict[str, Any], int]:
    """The state written by :func:`write_checkpoint` and its frame-list position. Nothing read
    can run code; a checkpoint that is missing, damaged, of another format or version raises
    :class:`CheckpointError` saying what was found."""
    run_dir = Path(run_dir)
    folder = run_dir / CHECKPOINT_DIR
    if not (folder / STATE_FILE).is_file():
        if (folder / OLD_STATE_FILE).is_file():
            raise CheckpointError(
                f"{folder / OLD_STATE_FILE}: a checkpoint in the old pickle format, which this "
                f"version does not load (loading a pickle can run any code); {_RESTART}"
            )
        raise CheckpointError(
            f"{run_dir}: no checkpoint to resume from ({folder / STATE_FILE} is missing); "
            "runs write one every N frames with `slam run --checkpoint-every N`"
        )
    _inside(run_dir, folder, "the checkpoint folder")
    header = _read_header(folder)
    current = folder / STATE_FILE
    try:
        current = folder / _own_name(header["arrays"], _STATE_ARRAYS, "arrays")
        _inside(run_dir, current, "the state's arrays")
        _verified(folder, header, current.name)
        core = decode(header["state"], _read_npz(current))
        if not isinstance(core, dict) or not isinstance(core.get("model"), dict):
            raise ValueError("the state is not a dict with a model")
        keyframes = []
        for name in _list(core["keyframes"]):
            current = folder / _own_name(name, _KEYFRAME, "keyframes")
            _inside(run_dir, current, "a keyframe file")
            _verified(folder, header, current.name)
            kf = _read_document(current)
            if not isinstance(kf, dict):
                raise ValueError("a keyframe is not a dict")
            keyframes.append(kf)
        current = folder / STATE_FILE
        submaps = []
        for j, sm in enumerate(_list(core["model"]["submaps"])):
            sm = dict(sm)
            if sm["volume"] is not None:
                current = folder / _own_name(sm["volume"], _VOLUME, f"submap {j} volume")
                _verified(folder, header, current.name)
                sm["volume"] = _read_npz(current)
                current = folder / STATE_FILE
            if sm.get("path") is not None:
                path = _in_run(run_dir, sm["path"], f"{current}: submap {sm['id']} path")
                if not path.is_file():
                    raise CheckpointError(
                        f"{current}: submap file {path} is missing (spilled submaps stay in "
                        f"RUN_DIR/submaps/ until the run ends); {_RESTART}"
                    )
                _inside(run_dir, path, "a spilled submap file")
                current = path
                _check_volume_file(path)
                current = folder / STATE_FILE
                sm["path"] = str(path)
            submaps.append(sm)
        position = int(header["position"])
        every = int(header.get("checkpoint_every", 0))
    except CheckpointError:
        raise
    except Exception as exc:  # any damage: a clear error, never a traceback or a guess
        raise CheckpointError(
            f"{current}: damaged checkpoint ({type(exc).__name__}: {exc}); {_RESTART}"
        ) from None
    state = {**core, "keyframes": keyframes, "model": {**core["model"], "submaps": submaps}}
    state["checkpoint_every"] = every
    return state, position
