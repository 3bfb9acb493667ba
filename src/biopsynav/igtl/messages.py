"""OpenIGTLink message types: one registry, pyigtl's classes plus the ones it lacks or packs wrong.

``MESSAGE_TYPES`` maps a type name of the header to the pyigtl ``MessageBase`` subclass that
unpacks its content; the reader decodes those and skips (validly framed) others. Add a type with
:func:`register_message` (in the style of meshio's ``register_format``).

Registered here beside pyigtl's TRANSFORM, STRING, POINT and POSITION:

* ``POLYDATA`` (:class:`TriangleMesh`): points and triangles, packed big-endian and vectorised
  (pyigtl's class packs vertex cells little-endian and loops in Python per cell);
* ``COMMAND`` / ``RTS_COMMAND`` (:class:`CommandMessage`), OpenIGTLink v3: a command id, a name of
  at most 128 bytes and a text (UTF-8), header version 2.

Layouts (big-endian), from the OpenIGTLink protocol description::

    POLYDATA  10 x uint32 (npoints, nvertices, size_vertices, nlines, size_lines, npolygons,
              size_polygons, ntriangle_strips, size_triangle_strips, nattributes),
              float32 points (npoints, 3), then each cell list as uint32 (n, i1 ... in)
    COMMAND   uint32 id, char[128] name, uint16 encoding (IANA MIBenum), uint32 length, text
"""

from __future__ import annotations

import struct

import numpy as np
import pyigtl

MESSAGE_TYPES: dict[str, type[pyigtl.MessageBase]] = {}

POLY_HEADER = struct.Struct(">10I")
COMMAND_HEADER = struct.Struct(">I128sHI")
COMMAND_NAME_BYTES = 128
MIB_US_ASCII = 3
MIB_UTF8 = 106


def register_message(type_name: str, cls: type[pyigtl.MessageBase]) -> None:
    """Decode messages of header type ``type_name`` with ``cls`` (a pyigtl ``MessageBase``)."""
    if len(type_name.encode("ascii")) > 12:
        raise ValueError(f"message type {type_name!r} is longer than 12 bytes")
    MESSAGE_TYPES[type_name] = cls


class TriangleMesh(pyigtl.MessageBase):
    """POLYDATA of one triangle mesh: ``points`` (n, 3) mm, ``triangles`` (m, 3) indices."""

    def __init__(self, points: np.ndarray | None = None, triangles: np.ndarray | None = None,
                 timestamp: float | None = None, device_name: str | None = None) -> None:
        super().__init__(timestamp=timestamp, device_name=device_name)
        self._message_type = "POLYDATA"
        self.points = np.zeros((0, 3)) if points is None else np.asarray(points).reshape(-1, 3)
        self.triangles = (np.zeros((0, 3), dtype=np.int64) if triangles is None
                          else np.asarray(triangles).reshape(-1, 3))
        self._valid_message = True

    def content_asstring(self) -> str:
        return f"Points: {len(self.points)}\nTriangles: {len(self.triangles)}\n"

    def _pack_content(self) -> bytes:
        n, m = len(self.points), len(self.triangles)
        cells = np.empty((m, 4), dtype=">u4")
        cells[:, 0] = 3
        cells[:, 1:] = self.triangles
        head = POLY_HEADER.pack(n, 0, 0, 0, 0, m, cells.nbytes, 0, 0, 0)
        return head + np.ascontiguousarray(self.points, dtype=">f4").tobytes() + cells.tobytes()

    def _unpack_content(self, content: bytes) -> None:
        self.points, polygons = unpack_polydata(content)
        self.triangles = polygons_to_triangles(polygons)


def unpack_polydata(content: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) float32 and the polygon cell list (uint32, ``n, i1 ... in`` per cell) of a
    POLYDATA body; ValueError when the sizes do not add up or an index is out of range."""
    if len(content) < POLY_HEADER.size:
        raise ValueError(f"POLYDATA content is {len(content)} bytes, shorter than its header")
    npts, _, s_vert, _, s_line, npoly, s_poly, _, s_strip, nattr = POLY_HEADER.unpack_from(content)
    start = POLY_HEADER.size + 12 * npts + s_vert + s_line
    if nattr == 0 and start + s_poly + s_strip != len(content):
        raise ValueError(f"POLYDATA sizes add up to {start + s_poly + s_strip} bytes, the content "
                         f"is {len(content)}")
    points = np.frombuffer(content, ">f4", 3 * npts, POLY_HEADER.size).reshape(-1, 3)
    polygons = np.frombuffer(content, ">u4", s_poly // 4, start)
    if len(_cell_starts(polygons)) != npoly:
        raise ValueError(f"POLYDATA announces {npoly} polygons, its cell list holds "
                         f"{len(_cell_starts(polygons))}")
    return points, polygons


def _cell_starts(cells: np.ndarray) -> list[int]:
    """Offsets of the cells of an ``n, i1 ... in`` list; ValueError when it overruns."""
    starts, at = [], 0
    while at < len(cells):
        starts.append(at)
        at += int(cells[at]) + 1
    if at != len(cells):
        raise ValueError("POLYDATA cell list overruns its size")
    return starts


def polygons_to_triangles(polygons: np.ndarray) -> np.ndarray:
    """(m, 3) int64 triangles of a cell list whose cells are all triangles."""
    if len(polygons) % 4 or np.any(polygons[::4] != 3):
        raise ValueError("POLYDATA polygons are not all triangles")
    return polygons.reshape(-1, 4)[:, 1:].astype(np.int64)


class CommandMessage(pyigtl.MessageBase):
    """COMMAND (or, with ``reply=True``, RTS_COMMAND): ``command_id``, ``command_name``,
    ``command`` text. Header version 2, as OpenIGTLink v3 sends it."""

    def __init__(self, command_name: str = "", command: str = "", command_id: int = 0,
                 reply: bool = False, timestamp: float | None = None,
                 device_name: str | None = None) -> None:
        super().__init__(timestamp=timestamp, device_name=device_name)
        self._message_type = "RTS_COMMAND" if reply else "COMMAND"
        self.header_version = 2
        self.command_id = int(command_id)
        self.command_name = command_name
        self.command = command
        self._valid_message = True

    def content_asstring(self) -> str:
        return f"Id: {self.command_id}\nName: {self.command_name}\nCommand: {self.command}\n"

    def _pack_content(self) -> bytes:
        name = self.command_name.encode("ascii")
        if len(name) > COMMAND_NAME_BYTES:
            raise ValueError(f"command name {self.command_name!r} is longer than 128 bytes")
        text = self.command.encode("utf-8")
        mib = MIB_US_ASCII if text.isascii() else MIB_UTF8
        return COMMAND_HEADER.pack(self.command_id, name, mib, len(text)) + text

    def _unpack_content(self, content: bytes) -> None:
        if len(content) < COMMAND_HEADER.size:
            raise ValueError(f"{self._message_type} content is {len(content)} bytes, shorter "
                             "than its 138-byte header")
        self.command_id, name, _mib, length = COMMAND_HEADER.unpack_from(content)
        text = content[COMMAND_HEADER.size:]
        if len(text) != length:
            raise ValueError(f"{self._message_type} text is {len(text)} bytes, its length "
                             f"field says {length}")
        self.command_name = name.rstrip(b"\0").decode("ascii")
        self.command = text.decode("utf-8")


class CommandReply(CommandMessage):
    """RTS_COMMAND: the answer to a COMMAND, with the command's id and name."""

    def __init__(self, command_name: str = "", command: str = "", command_id: int = 0,
                 timestamp: float | None = None, device_name: str | None = None) -> None:
        super().__init__(command_name, command, command_id, True, timestamp, device_name)


register_message("TRANSFORM", pyigtl.TransformMessage)
register_message("STRING", pyigtl.StringMessage)
register_message("POINT", pyigtl.PointMessage)
register_message("POSITION", pyigtl.PositionMessage)
register_message("POLYDATA", TriangleMesh)
register_message("COMMAND", CommandMessage)
register_message("RTS_COMMAND", CommandReply)
