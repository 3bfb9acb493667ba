"""OpenIGTLink framing: header validation, partial reads, CRC, encoding with pyigtl."""

from __future__ import annotations

import socket
import struct
import threading

import numpy as np
import pyigtl
import pytest

from biopsynav.igtl.protocol import (
    HEADER_SIZE,
    ConnectionClosed,
    IgtlProtocolError,
    MessageReader,
    encode_string,
    encode_transform,
    pack,
    parse_header,
    points_message,
    read_message,
)

T = np.array([[0.0, -1, 0, 10], [1, 0, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1]])


def test_transform_round_trip_byte_by_byte():
    data = encode_transform("ProbeToReference", T, timestamp=12.5)
    assert struct.unpack(">H", data[:2])[0] == 1  # header version 1
    reader = MessageReader()
    got = []
    for i in range(len(data)):
        got += reader.feed(data[i:i + 1])
    assert len(got) == 1 and reader.pending == 0
    msg = got[0]
    assert (msg.type, msg.device, msg.header.timestamp) == ("TRANSFORM", "ProbeToReference", 12.5)
    np.testing.assert_allclose(msg.body.matrix, T)


def test_several_messages_in_one_feed_and_point_lists():
    data = (pack(points_message("Lesions", np.zeros((2, 3)), ["Lesion1", "Lesion2"],
                                rgba=[[0, 200, 0, 255]] * 2, diameters=[5.0, 5.0]))
            + encode_string("TrackingStatus", "ok"))
    got = MessageReader().feed(data)
    assert [m.type for m in got] == ["POINT", "STRING"]
    assert got[0].body.names == ["Lesion1", "Lesion2"]
    assert got[1].body.string == "ok"


@pytest.mark.parametrize("mutate, match", [
    (lambda h: b"\x00\x07" + h[2:], "version 7"),
    (lambda h: h[:2] + b"TRANS\x01FORM\0\0" + h[14:], "type name"),
    (lambda h: h[:2] + b"\0" * 12 + h[14:], "empty type"),
    (lambda h: h[:14] + b"Probe\0X" + b"\0" * 13 + h[34:], "device name"),
    (lambda h: h[:42] + struct.pack(">Q", 1 << 40) + h[50:], "oversized body"),
])
def test_bad_headers_are_named(mutate, match):
    header = encode_transform("ProbeToReference", T)[:HEADER_SIZE]
    with pytest.raises(IgtlProtocolError, match=match) as info:
        parse_header(mutate(header))
    assert not info.value.resync


def test_reader_stops_after_malformed_header():
    reader = MessageReader()
    got = reader.feed(b"\xff" * 100)
    assert len(got) == 1 and isinstance(got[0], IgtlProtocolError) and not got[0].resync
    assert isinstance(reader.feed(encode_string("x", "y"))[0], IgtlProtocolError)


def test_wrong_crc_loses_only_that_message():
    bad = bytearray(encode_transform("ProbeToReference", T))
    bad[-1] ^= 0xFF
    got = MessageReader().feed(bytes(bad) + encode_string("S", "after"))
    assert isinstance(got[0], IgtlProtocolError) and got[0].resync
    assert "wrong CRC" in str(got[0])
    assert got[1].body.string == "after"


def test_unknown_type_is_returned_without_body_and_undecodable_body_resyncs():
    unknown = pyigtl.StringMessage("hi", device_name="X")
    unknown._message_type = "CUSTOMTYPE"
    short = pyigtl.StringMessage("", device_name="ProbeToReference")
    short._message_type = "TRANSFORM"  # a 4-byte TRANSFORM body cannot be decoded
    got = MessageReader().feed(unknown.pack() + short.pack())
    assert got[0].type == "CUSTOMTYPE" and got[0].body is None
    assert isinstance(got[1], IgtlProtocolError) and got[1].resync


def test_version_2_input_is_accepted():
    msg = pyigtl.TransformMessage(T, device_name="ProbeToReference")
    msg.header_version = 2
    got = MessageReader().feed(msg.pack())
    np.testing.assert_allclose(got[0].body.matrix, T)


def test_read_message_handles_partial_writes_and_vanishing_peers():
    a, b = socket.socketpair()
    data = encode_transform("ProbeToReference", T)
    with a, b:
        def trickle():
            for i in range(0, len(data), 7):
                b.sendall(data[i:i + 7])
            b.sendall(data[:HEADER_SIZE + 5])
            b.close()
        thread = threading.Thread(target=trickle)
        thread.start()
        a.settimeout(5)
        np.testing.assert_allclose(read_message(a).body.matrix, T)
        with pytest.raises(ConnectionClosed, match="middle of a message"):
            read_message(a)
        thread.join(5)


def test_device_name_longer_than_20_bytes_is_refused():
    with pytest.raises(ValueError, match="longer than 20"):
        encode_transform("Lesion123456ToReference", T)
