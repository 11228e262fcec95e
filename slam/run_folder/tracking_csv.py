"""``tracking.csv``: the per-frame :class:`~slam.records.TrackingStatus` records of a run, one
row each, columns in the record's field order. The one converter both ways: :func:`format_rows`
(what the run writes) and :func:`parse_rows` (what ``slam report``, ``slam view`` and
``render_run`` read back), plus :func:`columns` for plots."""

from __future__ import annotations

import csv
import dataclasses
import io
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import RunFolderError
from slam.records import TrackingStatus
from slam.run_folder.layout import TRACKING_FILE

__all__ = ["columns", "format_rows", "parse_rows", "read_tracking_csv"]

_FIELDS = {f.name: f for f in dataclasses.fields(TrackingStatus)}
_TRUE = ("True", "true", "1")


def format_rows(statuses: Sequence[TrackingStatus]) -> str:
    """The CSV text of ``statuses``: a header of the record's fields, one row per status
    (booleans as ``True``/``False``); empty text for no statuses."""
    if not statuses:
        return ""
    buf = io.StringIO()
    rows = [s.as_row() for s in statuses]
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _value(kind: Any, text: str) -> Any:
    if kind in ("bool", bool):
        return text in _TRUE
    if kind in ("int", int):
        return int(float(text))
    if kind in ("float", float):
        return float(text)
    return text


def parse_rows(text: str | Iterable[str], where: str = TRACKING_FILE) -> list[TrackingStatus]:
    """The :class:`TrackingStatus` records of CSV text (as :func:`format_rows` writes it).

    Columns that are not fields of the record are ignored and empty cells (or missing columns)
    take the field's default; a malformed cell, or a row without ``index``, ``path`` and
    ``ok``, is a :class:`RunFolderError` naming ``where`` and the line."""
    lines = io.StringIO(text) if isinstance(text, str) else text
    out = []
    reader = csv.DictReader(lines)
    for row in reader:
        kw: dict[str, Any] = {}
        for name, cell in row.items():
            f = _FIELDS.get(name) if isinstance(name, str) else None
            if f is None or cell is None or cell == "":
                continue
            try:
                kw[name] = _value(f.type, cell)
            except ValueError as exc:
                raise RunFolderError(
                    f"{where}, line {reader.line_num}: column {name}: cannot read {cell!r} "
                    f"({exc}); the file is damaged: run the sequence again"
                ) from exc
        try:
            out.append(TrackingStatus(**kw))
        except TypeError as exc:
            raise RunFolderError(
                f"{where}, line {reader.line_num}: a row needs index, path and ok ({exc}); "
                f"is it the {TRACKING_FILE} of `slam run`?"
            ) from exc
    return out


def read_tracking_csv(path: str | Path) -> list[TrackingStatus]:
    """:func:`parse_rows` of the file at ``path``."""
    path = Path(path)
    try:
        with path.open(newline="") as f:
            return parse_rows(f, str(path))
    except OSError as exc:
        raise RunFolderError(f"{path}: cannot read: {exc}") from exc


def columns(statuses: Sequence[TrackingStatus]) -> dict[str, np.ndarray]:
    """The records as columns: numbers and booleans as float arrays (booleans 0/1), text as
    string arrays; ``{}`` for no records."""
    if not statuses:
        return {}
    out: dict[str, np.ndarray] = {}
    for name, f in _FIELDS.items():
        values = [getattr(s, name) for s in statuses]
        if f.type in ("str", str):
            out[name] = np.array(values, dtype=str)
        else:
            out[name] = np.array(values, dtype=float)
    return out
