"""OpenIGTLink framing: header validation, exact body reads, CRC-64, pyigtl (de)coding.

Wire format (OpenIGTLink header; version 2 bodies start with a 12-byte extended header and end
with the metadata, both read and written here through pyigtl)::

    offset size field
    0      2    header version (big-endian uint16; 1 or 2)
    2      12   message type, ASCII, NUL padded (TRANSFORM, STRING, POINT, ...)
    14     20   device name, NUL padded
    34     8    timestamp (uint32 seconds, uint32 fraction)
    42     8    body size (uint64)
    50     8    CRC-64 (ECMA-182) of the body
    58     ...  body

Only message classes (pyigtl's and those of :mod:`.messages`, one registry) pack and unpack
content; pyigtl's transport (threads with sleeps) is not used. :class:`MessageReader` is an
incremental parser for non-blocking sockets; :func:`read_message` reads one message from a
blocking socket.

Errors are :class:`IgtlProtocolError`. Its ``resync`` flag says whether the byte stream is
still framed correctly after the error (a wrong CRC or an undecodable body of a known size:
only that message is lost) or not (a malformed header, an oversized body: the connection
must be dropped).
"""

from __future__ import annotations

import socket
import string
import struct
from dataclasses import dataclass

import numpy as np
import pyigtl
from pyigtl.messages import CRC64

from ..errors import BiopsynavError
from .messages import MESSAGE_TYPES

HEADER_SIZE = 58
HEADER_STRUCT = struct.Struct(">H12s20sIIQQ")
ACCEPTED_HEADER_VERSIONS = (1, 2)
DEVICE_NAME_BYTES = 20
DEFAULT_MAX_BODY_BYTES = 1 << 20

_TYPE_CHARS = frozenset((string.ascii_uppercase + string.ascii_lowercase + string.digits
                         + "_").encode())
_DEVICE_CHARS = frozenset(range(0x20, 0x7F))


class IgtlProtocolError(BiopsynavError):
    """A message that breaks the protocol; ``resync`` is True when only that message is lost."""

    def __init__(self, what: str, where: str | None = None, *, resync: bool = False) -> None:
        super().__init__(what, where)
        self.resync = resync


class ConnectionClosed(BiopsynavError):
    """The peer closed the connection; ``pending`` bytes of an incomplete message were lost."""

    def __init__(self, pending: int = 0) -> None:
        what = "peer closed the connection"
        if pending:
            what += f" in the middle of a message ({pending} bytes of it received)"
        super().__init__(what)
        self.pending = pending


@dataclass(frozen=True)
class Header:
    """A validated OpenIGTLink header."""

    version: int
    type: str
    device: str
    timestamp: float
    body_size: int
    crc: int

    def fields(self) -> dict:
        """The header in the dict form pyigtl's ``MessageBase.unpack`` takes."""
        return {"header_version": self.version, "message_type": self.type,
                "device_name": self.device, "timestamp": self.timestamp,
                "body_size": self.body_size}


@dataclass
class Message:
    """One received message: its header and the pyigtl object (None for a skipped type)."""

    header: Header
    body: pyigtl.MessageBase | None

    @property
    def type(self) -> str:
        return self.header.type

    @property
    def device(self) -> str:
        return self.header.device


def _padded_field(raw: bytes, allowed: frozenset, what: str) -> str:
    """Decode a NUL-padded header text field; raise when it holds anything else."""
    text, _, padding = raw.partition(b"\0")
    if padding.strip(b"\0"):
        raise IgtlProtocolError(f"{what} has bytes after its NUL terminator: {raw!r}")
    if not all(c in allowed for c in text):
        raise IgtlProtocolError(f"{what} holds invalid characters: {raw!r}")
    return text.decode("ascii")


def parse_header(data: bytes, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> Header:
    """Validate and decode a 58-byte header; raise :class:`IgtlProtocolError` naming the fault."""
    if len(data) != HEADER_SIZE:
        raise IgtlProtocolError(f"header is {len(data)} bytes, expected {HEADER_SIZE}")
    version, raw_type, raw_device, sec, frac, body_size, crc = HEADER_STRUCT.unpack(data)
    if version not in ACCEPTED_HEADER_VERSIONS:
        raise IgtlProtocolError(f"malformed header: version {version} is not one of "
                                f"{ACCEPTED_HEADER_VERSIONS}")
    msg_type = _padded_field(raw_type, _TYPE_CHARS, "malformed header: type name")
    if not msg_type:
        raise IgtlProtocolError("malformed header: empty type name")
    device = _padded_field(raw_device, _DEVICE_CHARS, "malformed header: device name")
    if body_size > max_body_bytes:
        raise IgtlProtocolError(f"oversized body: {msg_type} {device!r} announces "
                                f"{body_size} bytes, the limit is {max_body_bytes}")
    timestamp = sec + frac / 2.0**32
    return Header(version, msg_type, device, timestamp, body_size, crc)


def decode_body(header: Header, body: bytes) -> Message:
    """Check the CRC and decode ``body`` with pyigtl; unknown types give ``Message(h, None)``."""
    if len(body) != header.body_size:
        raise IgtlProtocolError(f"body is {len(body)} bytes, header says {header.body_size}",
                                resync=True)
    cls = MESSAGE_TYPES.get(header.type)
    if cls is None:
        return Message(header, None)
    crc = CRC64(body)
    if crc != header.crc:
        raise IgtlProtocolError(f"wrong CRC in {header.type} {header.device!r}: header "
                                f"{header.crc:#018x}, body {crc:#018x}", resync=True)
    msg = cls()
    try:
        msg.unpack(header.fields(), body)
    except Exception as exc:  # pyigtl raises struct.error, ValueError, TypeError ...
        raise IgtlProtocolError(f"cannot decode {header.type} {header.device!r} "
                                f"({header.body_size} bytes): {exc}", resync=True) from None
    return Message(header, msg)


class MessageReader:
    """Incremental parser for one connection: :meth:`feed` bytes, get whole messages back.

    The buffer never holds more than one header, one body of at most ``max_body_bytes`` and
    the bytes of the last ``feed``; the header is validated as soon as its 58 bytes are in.
    """

    def __init__(self, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
        self.max_body_bytes = max_body_bytes
        self._buf = bytearray()
        self._header: Header | None = None
        self._broken = False

    @property
    def pending(self) -> int:
        """Bytes of an incomplete message held."""
        return len(self._buf) + (HEADER_SIZE if self._header is not None else 0)

    def feed(self, data: bytes) -> list[Message | IgtlProtocolError]:
        """Add received bytes; return the complete messages and the errors, in order.

        A non-resyncable error (malformed header, oversized body) ends the list; the reader is
        then unusable and the connection must be closed.
        """
        if self._broken:
            return [IgtlProtocolError("stream is no longer framed after an earlier error")]
        self._buf += data
        out: list[Message | IgtlProtocolError] = []
        while True:
            if self._header is None:
                if len(self._buf) < HEADER_SIZE:
                    return out
                raw = bytes(self._buf[:HEADER_SIZE])
                del self._buf[:HEADER_SIZE]
                try:
                    self._header = parse_header(raw, self.max_body_bytes)
                except IgtlProtocolError as exc:
                    self._broken = True
                    self._buf.clear()
                    out.append(exc)
                    return out
            size = self._header.body_size
            if len(self._buf) < size:
                return out
            body = bytes(self._buf[:size])
            del self._buf[:size]
            header, self._header = self._header, None
            try:
                out.append(decode_body(header, body))
            except IgtlProtocolError as exc:
                out.append(exc)


def recv_exactly(sock: socket.socket, size: int) -> bytes:
    """Read exactly ``size`` bytes from a blocking socket; :class:`ConnectionClosed` if it ends."""
    buf = bytearray()
    while len(buf) < size:
        chunk = sock.recv(min(size - len(buf), 1 << 16))
        if not chunk:
            raise ConnectionClosed(len(buf))
        buf += chunk
    return bytes(buf)


def read_message(sock: socket.socket, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> Message:
    """Read one whole message from a blocking socket (partial reads handled)."""
    header = parse_header(recv_exactly(sock, HEADER_SIZE), max_body_bytes)
    try:
        body = recv_exactly(sock, header.body_size)
    except ConnectionClosed as exc:
        raise ConnectionClosed(HEADER_SIZE + exc.pending) from None
    return decode_body(header, body)


def pack(msg: pyigtl.MessageBase, version: int = 1, metadata: dict | None = None) -> bytes:
    """Pack ``msg`` with header ``version`` (1, or 2 with ``metadata``: str keys and values),
    checking that the device name fits its 20 bytes."""
    if len(msg.device_name.encode("utf-8")) > DEVICE_NAME_BYTES:
        raise ValueError(f"device name {msg.device_name!r} is longer than "
                         f"{DEVICE_NAME_BYTES} bytes")
    msg.header_version = version
    msg.metadata = dict(metadata or {}) if version >= 2 else {}
    return msg.pack()


def transform_message(device: str, matrix: np.ndarray,
                      timestamp: float | None = None) -> pyigtl.TransformMessage:
    """A TRANSFORM (4 x 4 homogeneous matrix, mm)."""
    return pyigtl.TransformMessage(np.asarray(matrix, dtype=np.float64), timestamp=timestamp,
                                   device_name=device)


def string_message(device: str, text: str, timestamp: float | None = None
                   ) -> pyigtl.StringMessage:
    """A STRING (ASCII, or UTF-8 when needed; cut to 65,535 bytes)."""
    data = text.encode("utf-8")
    if len(data) > 0xFFFF:
        text = data[:0xFFFF].decode("utf-8", errors="ignore")
    return pyigtl.StringMessage(text, timestamp=timestamp, device_name=device)


def points_message(device: str, positions: np.ndarray, names: list[str],
                   rgba: list[list[int]] | None = None, diameters: list[float] | None = None,
                   groups: list[str] | None = None, timestamp: float | None = None
                   ) -> pyigtl.PointMessage:
    """A POINT list; colours and diameters as plain lists (pyigtl rejects numpy arrays)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return pyigtl.PointMessage(positions=pos, names=list(names),
                               rgba_colors=[list(map(int, c)) for c in rgba] if rgba else None,
                               diameters=[float(d) for d in diameters] if diameters else None,
                               groups=list(groups) if groups else None,
                               timestamp=timestamp, device_name=device)


def encode_transform(device: str, matrix: np.ndarray, timestamp: float | None = None) -> bytes:
    """A TRANSFORM message, header version 1."""
    return pack(transform_message(device, matrix, timestamp))


def encode_string(device: str, text: str, timestamp: float | None = None) -> bytes:
    """A STRING message, header version 1."""
    return pack(string_message(device, text, timestamp))


class Outgoing:
    """One message to send, packed at most once per header version (on first demand).

    ``metadata`` goes out with version 2 only; ``min_version`` 2 for messages that exist only
    in OpenIGTLink v3 (RTS_COMMAND).
    """

    __slots__ = ("msg", "metadata", "min_version", "_packed")

    def __init__(self, msg: pyigtl.MessageBase, metadata: dict | None = None,
                 min_version: int = 1) -> None:
        self.msg = msg
        self.metadata = metadata or {}
        self.min_version = min_version
        self._packed: dict[int, bytes] = {}

    @property
    def type(self) -> str:
        return self.msg._message_type

    @property
    def device(self) -> str:
        return self.msg.device_name

    def packed(self, version: int) -> bytes:
        """The message with header ``version`` (raised to ``min_version``)."""
        version = max(version, self.min_version)
        data = self._packed.get(version)
        if data is None:
            data = self._packed[version] = pack(self.msg, version, self.metadata)
        return data
