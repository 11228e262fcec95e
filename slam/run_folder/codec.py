"""Plain data to JSON and numeric arrays, and back, without pickle: the checkpoint codec.

It takes nested plain data: dict (any keys of the types below; dicts with non-string keys keep
their key types), list, tuple, str, int (any size), float (nan and inf too), bool, None, numpy
scalars and numpy arrays of bool or numeric dtype. Anything else is refused when *encoding*,
naming where in the data it sits, so no component can put an object into a checkpoint; decoding
reads only JSON and arrays, so a doctored file cannot run code.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from slam.errors import RunFolderError

_TAG = "$t"  # JSON objects with this key are encoded values, not plain dicts
_ARRAY_KINDS = frozenset("biufc")  # bool, signed, unsigned, float, complex
_INLINE = 16  # arrays of at most this many elements are written into the JSON document


class CheckpointError(RunFolderError):
    """A checkpoint cannot be written (the state holds something that is not plain data) or
    read (missing, damaged, another format or version, or not a checkpoint at all)."""


# --- codec
class _Encoder:
    """Plain data to a JSON-able tree. Small arrays (poses, intrinsics) are written inline
    (exactly: float32 and float16 values are exact as Python floats), the others go to
    :attr:`arrays`, referenced by key. An array met twice comes back as one object, as with
    pickle (an inline one moves to :attr:`arrays` when met again)."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}
        self._memo: dict[int, dict[str, Any]] = {}  # the state keeps the arrays alive

    def _store(self, a: np.ndarray) -> str:
        key = f"a{len(self.arrays)}"
        self.arrays[key] = a
        return key

    def _array(self, a: np.ndarray) -> dict[str, Any]:
        node = self._memo.get(id(a))
        if node is not None:
            if "key" not in node:  # inline so far: store it once, refer to it twice
                data = {_TAG: "nd", "key": self._store(a)}
                node.clear()
                node.update(data)
            return {_TAG: "nd", "key": node["key"]}
        kind = a.dtype.kind
        if a.size <= _INLINE and kind in "biuf" and a.dtype.itemsize <= 8:
            node = {_TAG: "nd", "dtype": a.dtype.str, "shape": list(a.shape)}
            node["data"] = a.ravel().tolist()
        else:
            node = {_TAG: "nd", "key": self._store(a)}
        self._memo[id(a)] = node
        return node

    def encode(self, x: Any, where: str) -> Any:
        t = type(x)
        if x is None or t is bool or t is int or t is str or t is float:
            return x
        if t is list:
            return [self.encode(v, f"{where}[{i}]") for i, v in enumerate(x)]
        if t is dict:
            if _TAG not in x and all(type(k) is str for k in x):
                return {k: self.encode(v, f"{where}.{k}") for k, v in x.items()}
            return {
                _TAG: "dict",
                "items": [
                    [self.encode(k, f"{where} (key {k!r})"), self.encode(v, f"{where}[{k!r}]")]
                    for k, v in x.items()
                ],
            }
        if t is tuple:
            return {
                _TAG: "tuple",
                "items": [self.encode(v, f"{where}[{i}]") for i, v in enumerate(x)],
            }
        if t is np.ndarray:
            if x.dtype.kind not in _ARRAY_KINDS:
                raise CheckpointError(
                    f"cannot checkpoint {where}: a numpy array of dtype {x.dtype} (only bool and "
                    "numeric arrays are stored; the loader reads them with allow_pickle=False)"
                )
            return self._array(x)
        if isinstance(x, np.generic) and x.dtype.kind in _ARRAY_KINDS:
            kind, size = x.dtype.kind, x.dtype.itemsize
            if kind == "b":
                return {_TAG: "np", "dtype": x.dtype.str, "value": bool(x)}
            if kind in "iu":
                return {_TAG: "np", "dtype": x.dtype.str, "value": int(x)}
            if kind == "f" and size <= 8:  # exact as a Python float
                return {_TAG: "np", "dtype": x.dtype.str, "value": float(x)}
            return {_TAG: "np0", "key": self._store(np.asarray(x))}  # long double, complex
        raise CheckpointError(
            f"cannot checkpoint {where}: a {t.__module__}.{t.__qualname__} is not plain data "
            "(dict, list, tuple, str, int, float, bool, None, numpy scalar or numeric array); "
            "its component's state_dict() must turn it into plain data"
        )


def _dtype(spec: Any) -> np.dtype:
    if type(spec) is not str:
        raise ValueError(f"dtype {spec!r} is not a string")
    dt = np.dtype(spec)
    if dt.kind not in _ARRAY_KINDS or dt.hasobject:
        raise ValueError(f"dtype {spec!r} is not bool or numeric")
    return dt


def _check_keys(x: dict, *keys: str) -> None:
    if set(x) != {_TAG, *keys}:
        raise ValueError(f"encoded {x.get(_TAG)!r} has keys {sorted(x)}, expected {sorted(keys)}")


class _Decoder:
    """The inverse of :class:`_Encoder`: only JSON values and the given arrays come out."""

    def __init__(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.arrays = arrays

    def _array(self, key: Any) -> np.ndarray:
        if type(key) is not str:
            raise ValueError(f"array reference {key!r} is not a string")
        if key not in self.arrays:
            raise ValueError(f"array {key!r} is referenced but not stored")
        return self.arrays[key]

    def decode(self, x: Any) -> Any:
        t = type(x)
        if x is None or t is bool or t is int or t is str or t is float:
            return x
        if t is list:
            return [self.decode(v) for v in x]
        if t is not dict:
            raise ValueError(f"unexpected JSON value of type {t.__name__}")
        tag = x.get(_TAG)
        if tag is None:
            return {k: self.decode(v) for k, v in x.items()}
        if tag == "dict":
            _check_keys(x, "items")
            out = {}
            for item in _list(x["items"]):
                if type(item) is not list or len(item) != 2:
                    raise ValueError(f"dict item {item!r} is not a [key, value] pair")
                out[self.decode(item[0])] = self.decode(item[1])  # unhashable key: TypeError
            return out
        if tag == "tuple":
            _check_keys(x, "items")
            return tuple(self.decode(v) for v in _list(x["items"]))
        if tag == "nd" and "data" in x:
            _check_keys(x, "dtype", "shape", "data")
            dt, shape = _dtype(x["dtype"]), _list(x["shape"])
            flat = np.array(_list(x["data"]))
            if flat.ndim != 1 or (flat.size and flat.dtype.kind not in "biuf"):
                raise ValueError(f"inline array data of {flat.dtype} and shape {flat.shape}")
            if any(type(n) is not int or n < 0 for n in shape):
                raise ValueError(f"array shape {shape!r}")
            return flat.astype(dt).reshape(shape)
        if tag == "nd":
            _check_keys(x, "key")
            return self._array(x["key"])
        if tag == "np":
            _check_keys(x, "dtype", "value")
            dt, value = _dtype(x["dtype"]), x["value"]
            ok = {"b": (bool,), "i": (int,), "u": (int,), "f": (int, float)}.get(dt.kind, ())
            if type(value) not in ok:
                raise ValueError(f"numpy {dt} scalar with value {value!r}")
            return dt.type(value)
        if tag == "np0":
            _check_keys(x, "key")
            a = self._array(x["key"])
            if a.ndim != 0:
                raise ValueError(f"scalar array {x['key']!r} has shape {a.shape}")
            return a[()]
        raise ValueError(f"unknown encoded type {tag!r}")


def _list(x: Any) -> list:
    if type(x) is not list:
        raise ValueError(f"expected a JSON list, got {type(x).__name__}")
    return x


def encode(obj: Any, where: str = "state") -> tuple[Any, dict[str, np.ndarray]]:
    """``obj`` (plain data) as a JSON-able tree and the arrays it references, by key.
    Raises :class:`CheckpointError` naming the first value that is not plain data."""
    enc = _Encoder()
    return enc.encode(obj, where), enc.arrays


def decode(tree: Any, arrays: Mapping[str, np.ndarray]) -> Any:
    """The inverse of :func:`encode` (``ValueError`` or ``TypeError`` if ``tree`` is not one of
    its outputs or names an array that ``arrays`` lacks)."""
    return _Decoder(arrays).decode(tree)


# --- files
