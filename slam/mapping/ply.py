"""The header of a PLY mesh file, read to check a file against what it declares: the writer
(:func:`~slam.mapping.tsdf.write_mesh`) checks that Open3D wrote every byte (it reports success
on a file a full disk cut short), the run-folder reader refuses a cut file, or one whose header
declares more than its bytes can hold (10^11 vertices in a 1 kB file), before Open3D reads it
(it reads a short file into a partial mesh with one line on stderr, and allocates what a header
declares)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: bytes of each PLY scalar type
TYPE_BYTES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
    "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip
#: a header longer than this is not one a mesh writer makes
MAX_HEADER_BYTES = 65536


@dataclass(frozen=True)
class Element:
    """A PLY element: ``count`` of them, each ``fixed_bytes`` long (the scalars and the list
    lengths; in ASCII, the least: a digit and a space per property) plus ``list_item_bytes``
    per item of its lists."""

    name: str
    count: int
    fixed_bytes: int
    list_item_bytes: int


@dataclass(frozen=True)
class PlyHeader:
    format: str  # ascii, binary_little_endian or binary_big_endian
    header_bytes: int
    elements: tuple[Element, ...]

    def count(self, name: str) -> int:
        return sum(e.count for e in self.elements if e.name == name)

    def least_bytes(self) -> int:
        """The fewest bytes a file with this header can have (every list empty)."""
        return self.header_bytes + sum(e.count * e.fixed_bytes for e in self.elements)

    def triangle_mesh_bytes(self) -> int:
        """The bytes of a binary file with this header whose lists are triangles."""
        return self.header_bytes + sum(
            e.count * (e.fixed_bytes + 3 * e.list_item_bytes) for e in self.elements
        )


def read_ply_header(path: str | Path) -> PlyHeader:
    """The header of the PLY file at ``path``: a ValueError saying what is wrong when it is
    not one (an OSError when the file cannot be read)."""
    with open(path, "rb") as f:
        head = f.read(MAX_HEADER_BYTES)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY mesh (no 'ply ... end_header' in its first bytes)")
    stop = head.find(b"\n", end)
    fmt, elements = "", []
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        try:
            if words[:1] == ["format"]:
                fmt = words[1]
            elif words[:1] == ["element"]:
                elements.append([words[1], int(words[2]), 0, 0])
            elif words[:1] == ["property"] and elements:
                ascii_ = fmt == "ascii"
                if words[1] == "list":
                    elements[-1][2] += 2 if ascii_ else TYPE_BYTES[words[2]]
                    elements[-1][3] += 2 if ascii_ else TYPE_BYTES[words[3]]
                else:
                    elements[-1][2] += 2 if ascii_ else TYPE_BYTES[words[1]]
        except (IndexError, ValueError, KeyError):
            raise ValueError(f"a damaged PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"a PLY header without a known format ({fmt or 'none'})")
    if any(e[1] < 0 for e in elements):
        raise ValueError("a PLY header with a negative element count")
    header_bytes = stop + 1 if stop >= 0 else len(head)
    return PlyHeader(fmt, header_bytes, tuple(Element(*e) for e in elements))
