"""The reply to a pose: what goes out, in which order."""

from __future__ import annotations

import numpy as np

from biopsynav.igtl.protocol import MessageReader
from biopsynav.igtl.replies import encode_lesion_point, encode_lesion_transforms, encode_lesions
from biopsynav.igtl.server import IgtlServer
from biopsynav.tracker.result import LesionResult, TrackingResult


def result(status: str = "ok", centres=((1.0, 2.0, 3.0), (4.0, 5.0, 6.0))) -> TrackingResult:
    lesions = [LesionResult(i + 1, np.array(c), np.zeros(3), status)
               for i, c in enumerate(centres)]
    return TrackingResult(lesions, status, "" if status == "ok" else "why", 1.0)


def kinds(data: bytes) -> list[tuple[str, str]]:
    return [(m.type, m.device) for m in MessageReader().feed(data)]


def test_point_goes_out_before_the_transforms_are_packed():
    server = IgtlServer(tracker=None, tracker_addr=None)  # no side effects until start()
    server._last_reliable = False  # the first reliable reply also says "ok" once
    parts = list(server._reply_parts(result(), 7.5))
    assert len(parts) == 2
    assert kinds(parts[0]) == [("STRING", "TrackingStatus"), ("POINT", "Lesions")]
    assert kinds(parts[1]) == [("TRANSFORM", "Lesion1ToReference"),
                               ("TRANSFORM", "Lesion2ToReference")]
    tf = MessageReader().feed(parts[1])[1]
    assert np.allclose(np.array(tf.body.matrix)[:3, 3], [4, 5, 6])
    assert all(m.header.timestamp == 7.5 for m in MessageReader().feed(b"".join(parts)))
    assert parts[0][-len(encode_lesion_point(result(), 7.5)):] == \
        encode_lesion_point(result(), 7.5)
    assert encode_lesions(result(), 7.5) == (encode_lesion_point(result(), 7.5)
                                             + encode_lesion_transforms(result(), 7.5))


def test_unreliable_result_sends_status_and_red_points_but_no_transforms():
    server = IgtlServer(tracker=None, tracker_addr=None)
    parts = [p for p in server._reply_parts(result("out_of_envelope"), 1.0) if p]
    assert [kinds(p) for p in parts] == [[("STRING", "TrackingStatus"), ("POINT", "Lesions")]]


def test_result_that_cannot_be_encoded_becomes_an_error_status(monkeypatch):
    import biopsynav.igtl.server as srv

    def broken(*args, **kwargs):
        raise ValueError("cannot pack")

    server = IgtlServer(tracker=None, tracker_addr=None)
    monkeypatch.setattr(srv, "encode_lesion_transforms", broken)
    parts = list(server._reply_parts(result(), 1.0))  # POINT sent, TRANSFORMs fail
    assert kinds(parts[0])[-1] == ("POINT", "Lesions")
    error = MessageReader().feed(parts[-1])
    assert [(m.type, m.device) for m in error] == [("STRING", "TrackingStatus")]
    assert "unusable result" in error[0].body.string
    assert server.stats().tracker_failures == 1 and server._last_reliable is False
    monkeypatch.setattr(srv, "encode_lesion_point", broken)
    parts = list(server._reply_parts(result(), 2.0))  # nothing usable: the error alone
    assert [kinds(p) for p in parts] == [[("STRING", "TrackingStatus")]]
