"""The header of a PLY file and the size its body must have.

A truncated binary PLY is the usual damage a map file suffers (a copy cut short, a full disk),
and the readers do not all notice it: Open3D returns the rows it could read and a warning,
plyfile raises only when a row is cut. :func:`check_ply_size` compares the file's size with the
size its header declares before any reader trusts the file; the Gaussian map PLY
(``mapping/splat/ply.py``) and the mesh (``mapping/mesh.py``) both check through it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

# PLY scalar type -> bytes (both the old and the sized names)
TYPE_BYTES = {
    **dict.fromkeys(("char", "int8", "uchar", "uint8"), 1),
    **dict.fromkeys(("short", "int16", "ushort", "uint16"), 2),
    **dict.fromkeys(("int", "int32", "uint", "uint32", "float", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}
FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
MAX_HEADER_BYTES = 1 << 20


class PlyHeaderError(ValueError):
    """A PLY file's header is malformed, or its body does not have the size the header says."""


@dataclass(frozen=True)
class PlyProperty:
    name: str
    type: str  # the value type (of each entry, for a list)
    count_type: str | None = None  # a list's length type; None for a scalar


@dataclass(frozen=True)
class PlyElementHeader:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    def row_bytes(self, list_len: int) -> int:
        """Bytes of one binary row when every list holds ``list_len`` entries."""
        return sum(
            TYPE_BYTES[p.type]
            if p.count_type is None
            else TYPE_BYTES[p.count_type] + list_len * TYPE_BYTES[p.type]
            for p in self.properties
        )


@dataclass(frozen=True)
class PlyHeader:
    format: str  # one of FORMATS
    elements: tuple[PlyElementHeader, ...]
    comments: tuple[str, ...]
    header_bytes: int  # up to and including the newline after end_header

    def element(self, name: str) -> PlyElementHeader | None:
        return next((e for e in self.elements if e.name == name), None)

    def body_bytes(self, list_len: int = 3) -> int:
        """The binary body's size when every list holds ``list_len`` entries (3: triangles)."""
        return sum(e.count * e.row_bytes(list_len) for e in self.elements)


def read_ply_header(path: str | os.PathLike[str]) -> PlyHeader:
    """Parse the header of the PLY file ``path``; PlyHeaderError names what is wrong."""
    p = Path(path)
    with p.open("rb") as fh:
        head = fh.read(MAX_HEADER_BYTES)
    if not head.startswith(b"ply"):
        raise PlyHeaderError(f"{p}: not a PLY file (starts with {head[:8]!r}, expected b'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise PlyHeaderError(f"{p}: PLY header has no end_header in its first {len(head)} bytes")
    newline = head.find(b"\n", end)
    if newline < 0:
        raise PlyHeaderError(f"{p}: the file ends right after end_header")
    fmt, comments, elements = None, [], []
    lines = head[:end].decode("ascii", errors="replace").splitlines()[1:]
    for n, line in enumerate(lines, start=2):
        words = line.split()
        if not words or words[0] in ("obj_info",):
            continue
        where = f"{p}: header line {n} ({line.strip()!r})"
        if words[0] == "comment":
            comments.append(line.strip()[len("comment") :].strip())
        elif words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise PlyHeaderError(f"{where}: expected format {' | '.join(FORMATS)} 1.0")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyHeaderError(f"{where}: expected 'element NAME COUNT'")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyHeaderError(f"{where}: a property before any element")
            if words[1:2] == ["list"] and len(words) == 5 and {*words[2:4]} <= TYPE_BYTES.keys():
                elements[-1][2].append(PlyProperty(words[4], words[3], words[2]))
            elif len(words) == 3 and words[1] in TYPE_BYTES:
                elements[-1][2].append(PlyProperty(words[2], words[1]))
            else:
                raise PlyHeaderError(f"{where}: expected 'property TYPE NAME' or a list")
        else:
            raise PlyHeaderError(f"{where}: unknown keyword {words[0]!r}")
    if fmt is None:
        raise PlyHeaderError(f"{p}: PLY header has no format line")
    return PlyHeader(
        fmt,
        tuple(PlyElementHeader(name, count, tuple(props)) for name, count, props in elements),
        tuple(comments),
        newline + 1,
    )


def check_ply_size(
    path: str | os.PathLike[str], header: PlyHeader, list_len: int = 3, exact: bool = True
) -> None:
    """PlyHeaderError unless a binary PLY's size is the header's plus the body its element
    counts declare (each list holding ``list_len`` entries; with ``exact`` False, at least that
    size: lists may be longer). ASCII files are not checked: their rows have no fixed size."""
    if header.format == "ascii":
        return
    p = Path(path)
    want = header.header_bytes + header.body_bytes(list_len)
    got = p.stat().st_size
    if got < want or (exact and got != want):
        counts = ", ".join(f"element {e.name} {e.count}" for e in header.elements)
        cut = "truncated" if got < want else "longer than its header says"
        raise PlyHeaderError(
            f"{p}: {cut}: its header declares {counts} ({want} bytes), the file holds {got} bytes"
        )
