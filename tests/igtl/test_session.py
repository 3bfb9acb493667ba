"""The session without sockets: messages in, batches out (what a Slicer or PLUS user meets)."""

from __future__ import annotations

import logging
import struct

import numpy as np
import pyigtl
import pytest

from biopsynav.config import IgtlSection
from biopsynav.igtl.messages import CommandMessage, TriangleMesh, unpack_polydata
from biopsynav.igtl.protocol import MessageReader, pack
from biopsynav.igtl.session import IgtlSession
from biopsynav.tracker.result import LesionResult, TrackingResult
from tests.igtl.rigid import RigidLesionTracker

from .conftest import CENTERS, translation


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make_session(tracker=None, **settings) -> tuple[IgtlSession, Clock]:
    clock = Clock()
    cfg = IgtlSection(**{"skin_model_rate_hz": 0.0, **settings})
    session = IgtlSession(tracker or RigidLesionTracker(CENTERS), settings=cfg, clock=clock)
    return session, clock


def decoded(msg: pyigtl.MessageBase, version: int = 1, metadata: dict | None = None):
    (out,) = MessageReader().feed(pack(msg, version, metadata))
    return out


def pose(T: np.ndarray, version: int = 1, metadata: dict | None = None, device="ProbeToReference"):
    return decoded(pyigtl.TransformMessage(T, device_name=device), version, metadata)


def command_string(text: str):
    return decoded(pyigtl.StringMessage(text, device_name="biopsynavCommand"))


def sent(batches, version: int = 1) -> list[list]:
    """Each batch as the messages a client decodes from it."""
    return [MessageReader().feed(b"".join(m.packed(version) for m in msgs))
            for _, msgs in batches if msgs]


def kinds(batch) -> list[tuple[str, str]]:
    return [(m.type, m.device) for m in batch]


def test_reply_order_point_first_then_transforms_then_lesion_models():
    session, _ = make_session()
    session.add_peer("slicer")
    batches = sent(session.on_messages(session.add_peer("plus", True), [pose(np.eye(4))]))
    assert kinds(batches[0]) == [("STRING", "TrackingStatus"), ("POINT", "Lesions")]
    assert kinds(batches[1]) == [("TRANSFORM", f"Lesion{i}ToReference") for i in (1, 2, 3)]
    assert kinds(batches[2]) == [("POLYDATA", f"Lesion{i}") for i in (1, 2, 3)]
    mesh = batches[2][0].body
    assert len(mesh.points) == 42 and len(mesh.triangles) == 80  # icosphere, closed
    edges = np.sort(mesh.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    assert np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2)  # every edge twice
    np.testing.assert_allclose(mesh.points.mean(axis=0), CENTERS[0], atol=1e-5)


class BoundedTracker(RigidLesionTracker):
    """The rigid stand-in with a 95 % bound of 0.5 mm times the lesion's place in the list."""

    def update(self, T, with_surface=False, lesion_surfaces=True):
        result = super().update(T, with_surface, lesion_surfaces)
        for i, lesion in enumerate(result.lesions):
            lesion.bound_mm = 0.5 * (i + 1)
        return result


def test_each_lesion_model_comes_with_its_95_percent_shell():
    session, _ = make_session(BoundedTracker(CENTERS))
    session.add_peer("slicer")
    batches = sent(session.on_messages(session.add_peer("plus", True), [pose(np.eye(4))]))
    models = {m.device: m.body for m in batches[2]}
    assert list(models) == [f"Lesion{i}" for i in (1, 2, 3)] + \
        [f"Lesion{i}Bound" for i in (1, 2, 3)]
    for i in (1, 2, 3):
        lesion, shell = models[f"Lesion{i}"], models[f"Lesion{i}Bound"]
        np.testing.assert_array_equal(shell.triangles, lesion.triangles)
        np.testing.assert_allclose(np.linalg.norm(shell.points - lesion.points, axis=1),
                                   0.5 * i, atol=1e-3)
        radius = np.linalg.norm(lesion.points - CENTERS[i - 1], axis=1)
        np.testing.assert_allclose(np.linalg.norm(shell.points - CENTERS[i - 1], axis=1),
                                   radius + 0.5 * i, atol=1e-3)  # outwards, on a sphere


def test_no_shell_without_a_bound():
    """The stand-in tracker has no bound (NaN): lesion models alone, as before bounds."""
    session, _ = make_session()
    session.add_peer("slicer")
    batches = sent(session.on_messages(session.add_peer("plus", True), [pose(np.eye(4))]))
    assert not [m for b in batches for m in b if m.device.endswith("Bound")]


def test_lesion_models_follow_the_push_at_their_own_rate():
    session, clock = make_session(lesion_model_rate_hz=10.0)
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    list(session.on_messages(plus, [pose(np.eye(4))]))
    clock.t += 0.01
    batches = sent(session.on_messages(plus, [pose(translation(0, 0, 4))]))
    assert [k for b in batches for k in kinds(b) if k[0] == "POLYDATA"] == []  # 10 Hz: not yet
    clock.t += 0.1
    models = sent(session.on_messages(plus, [pose(translation(0, 0, 4))]))[-1]
    np.testing.assert_allclose(models[1].body.points.mean(axis=0), CENTERS[1] + [0, 0, 4],
                               atol=1e-5)


def test_skin_model_is_decimated_and_moved():
    import trimesh

    skin = trimesh.creation.icosphere(subdivisions=4, radius=60.0)  # 5,120 triangles
    tracker = RigidLesionTracker(CENTERS, skin=(skin.vertices, skin.faces))
    session, clock = make_session(tracker, skin_model_rate_hz=5.0, skin_model_triangles=500)
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    list(session.on_messages(plus, [pose(np.eye(4))]))
    clock.t += 0.2
    batches = sent(session.on_messages(plus, [pose(translation(0, 2, 0))]))
    (skin_msg,) = [m for b in batches for m in b if m.device == "BreastSkin"]
    assert 400 < len(skin_msg.body.triangles) <= 500
    assert trimesh.Trimesh(skin_msg.body.points, skin_msg.body.triangles).is_watertight
    radii = np.linalg.norm(skin_msg.body.points - [0, 2, 0], axis=1)
    np.testing.assert_allclose(radii, 60.0, rtol=5e-3)  # on the skin, moved rigidly


def test_prepare_decimates_the_skin_before_the_first_pose(monkeypatch):
    """The skin model is made before serving, never by the first reply after a pose (at
    100 Hz its first decimation, a few hundred ms, queued poses behind it)."""
    import trimesh

    import biopsynav.igtl.session as session_module

    skin = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    tracker = RigidLesionTracker(CENTERS, skin=(skin.vertices, skin.faces))
    prepared = []
    tracker.prepare_surface = lambda: prepared.append(True)  # the tracker's own skin work
    off, _ = make_session(tracker)  # skin model off: nothing to prepare
    off.prepare()
    assert prepared == []
    session, clock = make_session(tracker, skin_model_rate_hz=5.0, skin_model_triangles=300)
    session.prepare()
    assert prepared == [True]
    calls = []
    monkeypatch.setattr(session_module, "decimate", lambda *a: calls.append(a))
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    list(session.on_messages(plus, [pose(np.eye(4))]))
    clock.t += 0.3
    batches = sent(session.on_messages(plus, [pose(translation(0, 2, 0))]))
    assert [m for b in batches for m in b if m.device == "BreastSkin"]
    assert calls == [] and off._skin is None


def test_unreliable_lesion_keeps_its_slot_at_its_last_reliable_place():
    session, _ = make_session()
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    list(session.on_messages(plus, [pose(np.eye(4))]))

    class OneLost:
        has_rest_pose = True

        def update(self, T):
            nan = np.full(3, np.nan)
            lesions = [LesionResult(1, CENTERS[0] + 1, np.ones(3)),
                       LesionResult(2, nan, nan, "out_of_envelope"),
                       LesionResult(3, CENTERS[2] + 1, np.ones(3))]
            return TrackingResult(lesions, "ok")

    session.tracker = OneLost()
    point = sent(session.on_messages(plus, [pose(np.eye(4))]))[0][-1].body
    assert point.names == ["Lesion1", "Lesion2", "Lesion3"]
    np.testing.assert_allclose(point.positions, [CENTERS[0] + 1, CENTERS[1], CENTERS[2] + 1])
    assert point.groups == ["ok", "out_of_envelope", "ok"]
    assert [list(c[:3]) for c in point.rgba_colors] == [[0, 200, 0], [230, 0, 0], [0, 200, 0]]


def test_status_is_sent_on_change_and_as_keep_alive():
    session, clock = make_session(RigidLesionTracker(CENTERS, max_push_mm=20.0),
                                  status_keepalive_s=1.0, max_poses_per_read=1)
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)

    def statuses(T):
        clock.t += 0.02
        return [m.body.string for b in sent(session.on_messages(plus, [pose(T)]))
                for m in b if m.device == "TrackingStatus"]

    assert statuses(np.eye(4)) == ["rest"]
    assert statuses(translation(0, 0, 1)) == ["ok"]
    assert statuses(translation(0, 0, 2)) == []  # unchanged: nothing at 50 Hz
    assert statuses(translation(0, 0, 30))[0].startswith("out_of_envelope: probe pushed 30")
    assert statuses(translation(0, 0, 31)) == []
    clock.t += 1.0
    assert statuses(translation(0, 0, 32))[0].startswith("out_of_envelope: probe pushed 32")


def test_plus_invalid_transform_status_gives_probe_not_tracked_without_numbers():
    session, _ = make_session()
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    list(session.on_messages(plus, [pose(np.eye(4))]))
    calls = []
    session.tracker.update = lambda T, **kw: calls.append(T)
    occluded = pose(np.eye(4), 2, {"TransformStatus": "INVALID"})
    batches = sent(session.on_messages(plus, [occluded]))
    assert [kinds(b) for b in batches] == [[("STRING", "TrackingStatus")]]
    assert batches[0][0].body.string == ("probe_not_tracked: the tracking system reports "
                                         "TransformStatus=INVALID")
    assert calls == [] and session.stats.poses_not_tracked == 1
    assert sent(session.on_messages(plus, [occluded])) == []  # said once


def test_probe_silent_for_the_timeout_gives_probe_not_tracked_once():
    session, clock = make_session(probe_timeout_s=0.5)
    session.add_peer("slicer")
    assert session.deadline() == np.inf  # no pose yet: nothing to time out
    list(session.on_messages(session.add_peer("plus", True), [pose(np.eye(4))]))
    assert session.deadline() == pytest.approx(clock.t + 0.5)
    clock.t += 0.4
    assert list(session.on_timer()) == []
    clock.t += 0.2
    (batch,) = sent(session.on_timer())
    assert batch[0].body.string == "probe_not_tracked: no probe pose for 0.6 s"
    assert session.deadline() == np.inf and list(session.on_timer()) == []


def test_string_commands_work_when_repeated_with_a_counter():
    session, _ = make_session()
    client = session.add_peer("slicer")
    list(session.on_messages(client, [pose(np.eye(4))]))
    for n in (1, 2, 3):
        list(session.on_messages(client, [pose(translation(0, 0, n))]))
        (batch,) = sent(session.on_messages(client, [command_string(f"SetRestPose {n}")]))
        assert batch[0].device == "biopsynavReply"
        assert batch[0].body.string.startswith("SetRestPose: ok")
    assert session.stats.rest_poses_set == 4  # automatic, then three commands
    (batch,) = sent(session.on_messages(client, [command_string("ClearRestPose")]))
    assert batch[0].body.string.startswith("ClearRestPose: ok")
    assert not session.tracker.has_rest_pose
    (batch,) = sent(session.on_messages(client, [command_string("Explode now")]))
    assert "unknown command 'Explode'" in batch[0].body.string


def test_v3_command_gets_an_rts_command_reply_with_its_id():
    session, _ = make_session()
    client = session.add_peer("slicer")
    list(session.on_messages(client, [pose(np.eye(4))]))
    cmd = decoded(CommandMessage("GetStatus", '<Command Name="GetStatus"/>', 17,
                                 device_name="SlicerCmd"), 2)
    (batch,) = [b for b in sent(session.on_messages(client, [cmd]), version=client.version)]
    reply = batch[0]
    assert (reply.type, reply.device, reply.header.version) == ("RTS_COMMAND", "SlicerCmd", 2)
    assert (reply.body.command_id, reply.body.command_name) == (17, "GetStatus")
    assert 'Status="SUCCESS"' in reply.body.command and "rest pose set" in reply.body.command
    clear = decoded(CommandMessage("ClearRestPose", "", 18), 2)
    (batch,) = sent(session.on_messages(client, [clear]), version=2)
    assert batch[0].body.command_id == 18 and 'Status="SUCCESS"' in batch[0].body.command
    again = sent(session.on_messages(client, [decoded(CommandMessage("ClearRestPose", "", 19),
                                                      2)]), version=2)
    assert 'Status="SUCCESS"' in again[0][0].body.command  # repeated: runs again


def test_replies_are_v1_until_the_client_speaks_v2_then_carry_status_metadata():
    session, _ = make_session()
    client = session.add_peer("slicer")
    assert client.version == 1
    list(session.on_messages(client, [pose(np.eye(4))]))
    list(session.on_messages(client, [pose(translation(0, 0, 1), 2)]))
    assert client.version == 2
    batches = sent(session.on_messages(client, [pose(translation(0, 0, 2), 2)]), version=2)
    point = batches[0][-1]
    assert point.header.version == 2 and point.body.metadata["TrackingStatus"] == "ok"
    tf = batches[1][0]
    assert tf.body.metadata == {"TransformStatus": "OK", "TrackingStatus": "ok"}
    fixed, _ = make_session(reply_header_version="1")
    peer = fixed.add_peer("old slicer")
    list(fixed.on_messages(peer, [pose(np.eye(4), 2)]))
    assert peer.version == 1


def test_probe_under_another_device_name_is_named_once(caplog):
    session, _ = make_session()
    plus = session.add_peer("tracker server 127.0.0.1:18944", True)
    with caplog.at_level(logging.INFO, logger="biopsynav.igtl"):
        for _ in range(3):
            assert list(session.on_messages(plus, [pose(np.eye(4), device="Tracker")])) == []
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == ["tracker server 127.0.0.1:18944 sends TRANSFORM 'Tracker', ignored: "
                        "the probe pose is expected as 'ProbeToReference' (--device or [igtl] "
                        "probe_device)"]
    assert session.stats.messages_skipped == 3


def test_rest_pose_cleared_when_the_tracker_connection_is_lost():
    session, _ = make_session()
    session.add_peer("slicer")
    list(session.on_messages(session.add_peer("plus", True), [pose(np.eye(4))]))
    (batch,) = sent(session.tracker_down())
    assert batch[0].body.string.startswith("no_rest_pose: tracker connection lost")
    assert not session.tracker.has_rest_pose and session.stats.rest_poses_cleared == 1


def test_polydata_is_big_endian_as_the_protocol_says():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    body = TriangleMesh(points, tris, device_name="m")._pack_content()
    assert body[:40] == struct.pack(">10I", 4, 0, 0, 0, 0, 4, 64, 0, 0, 0)
    assert body[40:52] == struct.pack(">3f", 0, 0, 0) and body[52:64] == struct.pack(">3f", 1, 0, 0)
    assert body[88:104] == struct.pack(">4I", 3, 0, 2, 1)
    got_points, polygons = unpack_polydata(body)
    np.testing.assert_array_equal(got_points, points)
    with pytest.raises(ValueError, match="sizes add up"):
        unpack_polydata(body[:-4])


def test_result_that_cannot_be_encoded_becomes_an_error_status(monkeypatch):
    import biopsynav.igtl.session as ses

    session, _ = make_session()
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)

    def broken(*args, **kwargs):
        raise ValueError("cannot pack")

    monkeypatch.setattr(ses, "transform_messages", broken)
    batches = sent(session.on_messages(plus, [pose(np.eye(4))]))  # POINT sent, TRANSFORMs fail
    assert kinds(batches[0])[-1] == ("POINT", "Lesions")
    assert batches[-1][0].body.string == "tracker_error: unusable result: cannot pack"
    assert session.stats.tracker_failures == 1


def test_a_case_without_lesions_sends_skin_and_status_alone():
    """A breast modelled before any lesion was marked: poses are tracked, the deformed skin
    and the status go out, and no lesion message."""
    import trimesh

    skin = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    tracker = RigidLesionTracker(np.zeros((0, 3)), skin=(skin.vertices, skin.faces))
    session, clock = make_session(tracker, skin_model_rate_hz=5.0)
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    first = sent(session.on_messages(plus, [pose(np.eye(4))]))
    clock.t += 0.2
    batches = first + sent(session.on_messages(plus, [pose(translation(0, 2, 0))]))
    devices = {m.device for b in batches for m in b}
    assert {"BreastSkin", "TrackingStatus"} <= devices
    assert not any(d == "Lesions" or d.startswith("Lesion") for d in devices), devices

