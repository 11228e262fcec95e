"""Checkpoints of a run: the :class:`~slam.system.Slam` state in ``RUN_DIR/checkpoint/``.

Layout: ``state.pkl`` (everything small, plus the position in the frame list), one file per
keyframe (``kf_NNNNNN.pkl``: ORB features and depth; written once, keyframes never change) and
the blocks of the submaps held in memory (``volume_SSSS_K.npz``, K = the checkpoint's serial).
Submaps spilled to ``RUN_DIR/submaps/`` are final once written and only referenced. A checkpoint
is replaced atomically: new files first, then ``state.pkl`` by rename, then stale volume files
are removed, so a kill at any moment leaves the previous checkpoint or the new one, whole.

Checkpoints are pickles written by this package for the same run folder: load only your own.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import SlamError

log = logging.getLogger(__name__)

CHECKPOINT_DIR = "checkpoint"
STATE_FILE = "state.pkl"


def _atomic_pickle(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def write_checkpoint(
    run_dir: str | Path, state: dict[str, Any], position: int, every: int = 0
) -> Path:
    """Write ``state`` (from :meth:`Slam.state_dict`) with ``position``, the number of entries
    of the frame list already processed, and ``every``, the checkpoint interval (kept for the
    resumed run). Returns the checkpoint folder."""
    t0 = time.perf_counter()
    folder = Path(run_dir) / CHECKPOINT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    previous = _read_state_file(folder)
    serial = 0 if previous is None else int(previous["serial"]) + 1

    kf_files = []
    for kf in state["keyframes"]:
        name = f"kf_{kf['id']:06d}.pkl"
        if not (folder / name).is_file():
            _atomic_pickle(folder / name, kf)
        kf_files.append(name)
    submaps = []
    volume_files = set()
    for sm in state["model"]["submaps"]:
        sm = dict(sm)
        if sm["volume"] is not None:
            name = f"volume_{sm['id']:04d}_{serial}.npz"
            _atomic_npz(folder / name, sm["volume"])
            sm["volume"] = name
            volume_files.add(name)
        submaps.append(sm)
    core = {
        **state,
        "keyframes": kf_files,
        "model": {**state["model"], "submaps": submaps},
        "position": int(position),
        "serial": serial,
        "checkpoint_every": int(every),
    }
    _atomic_pickle(folder / STATE_FILE, core)
    for p in folder.glob("volume_*.npz"):
        if p.name not in volume_files:
            p.unlink(missing_ok=True)
    log.debug(
        "checkpoint %d at frame position %d written in %.0f ms",
        serial,
        position,
        (time.perf_counter() - t0) * 1e3,
    )
    return folder


def _read_state_file(folder: Path) -> dict[str, Any] | None:
    path = folder / STATE_FILE
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        raise SlamError(f"{path}: unreadable checkpoint ({exc}); start the run again") from exc


def has_checkpoint(run_dir: str | Path) -> bool:
    return (Path(run_dir) / CHECKPOINT_DIR / STATE_FILE).is_file()


def read_checkpoint(run_dir: str | Path) -> tuple[dict[str, Any], int]:
    """The state written by :func:`write_checkpoint` and its frame-list position."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    core = _read_state_file(folder)
    if core is None:
        raise SlamError(
            f"{run_dir}: no checkpoint to resume from ({folder / STATE_FILE} is missing); "
            "runs write one every N frames with `slam run --checkpoint-every N`"
        )
    try:
        keyframes = []
        for name in core["keyframes"]:
            with open(folder / name, "rb") as f:
                keyframes.append(pickle.load(f))
        submaps = []
        for sm in core["model"]["submaps"]:
            sm = dict(sm)
            if sm["volume"] is not None:
                with np.load(folder / sm["volume"]) as z:
                    sm["volume"] = {k: z[k] for k in z.files}
            elif sm["path"] is not None and not Path(sm["path"]).is_file():
                raise SlamError(f"submap file {sm['path']} is missing")
            submaps.append(sm)
    except (OSError, pickle.UnpicklingError, EOFError, KeyError, ValueError) as exc:
        raise SlamError(
            f"{folder}: incomplete or damaged checkpoint ({exc}); start the run again"
        ) from exc
    position = int(core.pop("position"))
    core.pop("serial", None)
    state = {**core, "keyframes": keyframes, "model": {**core["model"], "submaps": submaps}}
    return state, position
