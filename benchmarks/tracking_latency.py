"""Tracking latency: ``tracker.update()``, the FE engine, and the OpenIGTLink round trip.

    python benchmarks/tracking_latency.py [CASE_DIR] [--duration 60 | --quick] [--rate 100]
                                          [--poses poses.csv] [--updates 2000]
                                          [--push-mm 8] [--follow] [--result-name NAME]

* ``update``: ``Tracker.load(CASE_DIR).update`` over ``--updates`` poses, median and p99;
  with ``--follow`` the same poses again with ``[tracker] contact_follows_pose`` on (the
  contact set grows with the skin the face reaches; each grown set is built the first time it
  is met, and that build counts in the figures), and the number of poses that held extra skin.
* ``fem``: ``Tracker.load(CASE_DIR, engine="fem").update``, median of a few poses.
* round trip: a stand-in tracker server (PLUS) streams the probe TRANSFORM at ``--rate`` Hz for
  ``--duration`` s to the service (``run_service`` in a child process, as in the field); a
  listening client (Slicer stand-in) times each lesion POINT against the send time of the pose
  it answers (matched by the echoed timestamp). Lost = poses without a POINT (including poses
  the service coalesced because it fell behind).

Without CASE_DIR, or while ``biopsynav.tracker.Tracker`` does not exist, the update and FE parts
are skipped (reported as nan) and the round trip uses the rigid stand-in tracker
(``tests/igtl/rigid.py``), so it measures the service alone.

Poses: ``--poses`` reads the ``biopsynav track`` CSV (``frame, sequence, m00 ... m23``);
otherwise a synthetic sequence pushes up to ``--push-mm`` (8 mm) along the rest pose's beam
axis with a +-3 degree rock, the rest pose being ``tracker.rest_pose`` when the tracker has
one, else the probe placed over the case's first lesion (``--lesion``) as in Table 2
(:func:`biopsynav.evaluate.placement.place_probe`: face centre on the skin, beam towards the
lesion), else (no case) the identity.

The last line reads ``RESULT update_p50_ms=... update_p99_ms=... rtt_p50_ms=... rtt_p99_ms=...
lost=... fem_update_ms=...`` (with ``--follow`` also ``follow_p50_ms=... follow_p99_ms=...
follow_held=N/M``).
"""

from __future__ import annotations

import argparse
import csv
import math
import multiprocessing as mp
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

from biopsynav.igtl.protocol import MessageReader, encode_transform
from biopsynav.igtl.replies import POINT_DEVICE
from resultfile import write_result  # noqa: E402  (benchmarks/, this script's folder)
from speedprobe import speed_probes  # noqa: E402

HOST = "127.0.0.1"
PROBE_DEVICE = "ProbeToReference"
TS_BASE = 1_000_000  # pose k is sent with timestamp TS_BASE + k + 0.5 (exact in IGTL format)
LESION_CENTERS = np.array([[10.0, 20.0, 30.0], [-5.0, 0.0, 40.0], [0.0, -15.0, 25.0]])


# ------------------------------------------------------------------------------------ poses
def read_poses_csv(path: str | Path) -> np.ndarray:
    """Poses (N, 4, 4) from a ``frame, sequence, m00 ... m23`` CSV."""
    keys = [f"m{r}{c}" for r in range(3) for c in range(4)]
    poses = []
    with open(path, newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            T = np.eye(4)
            T[:3, :] = np.array([float(row[k]) for k in keys]).reshape(3, 4)
            poses.append(T)
    if not poses:
        raise SystemExit(f"{path}: no poses")
    return np.array(poses)


def synthetic_poses(rest: np.ndarray, n: int, rate_hz: float = 100.0,
                    push_mm: float = 8.0) -> np.ndarray:
    """Push (0 to ``push_mm`` along the rest beam axis, 2 s period) and rock (+-3 deg about
    probe x)."""
    t = np.arange(n) / rate_hz
    push = 0.5 * push_mm * (1 - np.cos(2 * np.pi * t / 2.0))
    angle = np.radians(3.0) * np.sin(2 * np.pi * t / 3.0)
    poses = np.empty((n, 4, 4))
    for k in range(n):
        local = np.eye(4)
        c, s = math.cos(angle[k]), math.sin(angle[k])
        local[1:3, 1:3] = [[c, -s], [s, c]]
        local[2, 3] = push[k]
        poses[k] = rest @ local
    return poses


def percentiles(values_ms: list[float] | np.ndarray) -> tuple[float, float]:
    if len(values_ms) == 0:
        return math.nan, math.nan
    return float(np.percentile(values_ms, 50)), float(np.percentile(values_ms, 99))


# ---------------------------------------------------------------------------------- tracker
def load_tracker(case_dir: str | None, engine: str | None = None):
    """``Tracker.load(case_dir[, engine=...])`` or None with the reason printed."""
    if case_dir is None:
        return None
    try:
        from biopsynav.tracker import Tracker
    except ImportError:
        print("  skipped: biopsynav.tracker.Tracker does not exist yet")
        return None
    return Tracker.load(case_dir) if engine is None else Tracker.load(case_dir, engine=engine)


def stand_in_tracker():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository
    from tests.igtl.rigid import RigidLesionTracker

    return RigidLesionTracker(LESION_CENTERS, max_push_mm=1e6)


def rest_pose_of(tracker, lesion: int = 0) -> np.ndarray:
    """The tracker's rest pose; else the probe over the case's lesion of index ``lesion``;
    else identity."""
    rest = getattr(tracker, "rest_pose", None)
    if rest is not None:
        return np.asarray(rest, dtype=np.float64)
    case = getattr(tracker, "case", None)
    if case is not None and len(case.anatomy.lesions):
        from biopsynav.evaluate.placement import place_case_probe

        return np.asarray(place_case_probe(case, lesion).pose, dtype=np.float64)
    return np.eye(4)


def time_updates(tracker, poses: np.ndarray, held: list | None = None) -> list[float]:
    """Milliseconds per ``update`` call (rest pose set at the first pose); ``held`` gets
    the number of skin vertices each update added to the contact set."""
    tracker.set_rest_pose(poses[0])
    tracker.update(poses[0])  # warm-up
    times = []
    for T in poses:
        t0 = time.perf_counter()
        tracker.update(T)
        times.append((time.perf_counter() - t0) * 1e3)
        if held is not None:
            held.append(len(tracker.last_touched))
    return times


def bench_update(args, poses_for) -> tuple[float, float]:
    print(f"update() over {args.updates} poses:")
    tracker = load_tracker(args.case_dir)
    if tracker is None:
        if args.case_dir is None:
            print("  skipped: no CASE_DIR given")
        return math.nan, math.nan
    p50, p99 = percentiles(time_updates(tracker, poses_for(tracker, args.updates)))
    print(f"  p50 {p50:.3f} ms  p99 {p99:.3f} ms")
    return p50, p99


def bench_follow(args, poses_for) -> tuple[float, float, str]:
    """``update`` with ``[tracker] contact_follows_pose`` on, over the same poses."""
    print(f"update() over {args.updates} poses, the contact set following the pose:")
    from biopsynav.case import Case
    from biopsynav.tracker import Tracker

    case = Case.load(args.case_dir)
    case.cfg.tracker.contact_follows_pose = True
    tracker, held = Tracker.load(case), []
    p50, p99 = percentiles(time_updates(tracker, poses_for(tracker, args.updates), held))
    share = f"{int(np.count_nonzero(held))}/{len(held)}"
    print(f"  p50 {p50:.3f} ms  p99 {p99:.3f} ms; poses holding extra skin {share} (up to "
          f"{max(held, default=0)} vertices, {len(tracker._grown)} grown sets)")
    return p50, p99, share


def bench_fem(args, poses_for) -> float:
    print("FE engine update():")
    tracker = load_tracker(args.case_dir, engine="fem")
    if tracker is None:
        if args.case_dir is None:
            print("  skipped: no CASE_DIR given")
        return math.nan
    poses = poses_for(tracker, 400)[::80]
    p50, _ = percentiles(time_updates(tracker, poses)[1:])
    print(f"  median {p50:.1f} ms over {len(poses)} poses")
    return p50


# ------------------------------------------------------------------------------- round trip
def _service_main(case_dir, plus_port: int, queue) -> None:
    """Child process: the OpenIGTLink service with the case tracker or the stand-in."""
    import logging

    from biopsynav.igtl.service import run_service, service_tracker

    logging.basicConfig(level=logging.WARNING, format="service: %(levelname)s %(message)s")
    tracker = None
    if case_dir is not None:
        try:
            import biopsynav.tracker  # noqa: F401  (absent: the stand-in below)
        except ImportError:
            pass
        else:
            tracker = service_tracker(case_dir)  # as `biopsynav serve` loads it
    if tracker is None:
        tracker = stand_in_tracker()
    stats = run_service(tracker, (HOST, plus_port), (HOST, 0), PROBE_DEVICE,
                        on_started=lambda server: queue.put(("address", server.address)))
    queue.put(("stats", stats.__dict__))


class RoundTrip:
    """Stand-in PLUS server and Slicer-like client around a service child process."""

    def __init__(self, poses: np.ndarray, rate_hz: float) -> None:
        self.poses = poses
        self.dt = 1.0 / rate_hz
        self.sent = np.full(len(poses), np.nan)
        self.received = np.full(len(poses), np.nan)
        self.sender_done = threading.Event()

    def send_loop(self, conn: socket.socket) -> None:
        """Send pose k at t0 + k dt (sleeping to the tick; the last bytes go out at once)."""
        t0 = time.perf_counter() + 0.05
        for k, T in enumerate(self.poses):
            delay = t0 + k * self.dt - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            data = encode_transform(PROBE_DEVICE, T, TS_BASE + k + 0.5)
            self.sent[k] = time.perf_counter()
            conn.sendall(data)
        self.sender_done.set()

    def receive_loop(self, client: socket.socket) -> None:
        """Record the arrival of every POINT until all are in or 1 s after the last send."""
        reader = MessageReader()
        client.settimeout(1.0)
        while np.isnan(self.received).any():
            try:
                data = client.recv(1 << 16)
            except TimeoutError:
                if self.sender_done.is_set():
                    return
                continue
            now = time.perf_counter()
            if not data:
                return
            for msg in reader.feed(data):
                if getattr(msg, "device", None) == POINT_DEVICE:
                    k = int(msg.header.timestamp) - TS_BASE
                    if 0 <= k < len(self.received):
                        self.received[k] = now


def bench_round_trip(args, poses_for) -> tuple[float, float, int]:
    n = int(round(args.duration * args.rate))
    label = "case tracker" if args.case_dir else "rigid stand-in tracker (service only)"
    print(f"OpenIGTLink round trip, {args.rate:g} Hz for {args.duration:g} s ({n} poses), "
          f"{label}:")
    tracker = None
    if args.case_dir is not None:
        tracker = load_tracker(args.case_dir)
    poses = poses_for(tracker or stand_in_tracker(), n)
    plus = socket.socket()
    plus.bind((HOST, 0))
    plus.listen(1)
    plus.settimeout(60)
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    child = ctx.Process(target=_service_main, args=(args.case_dir, plus.getsockname()[1], queue))
    child.start()
    try:
        kind, address = queue.get(timeout=120)
        client = socket.create_connection(tuple(address), timeout=10)
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn, _ = plus.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        _warm_up(conn, client, poses[0])
        rt = RoundTrip(poses, args.rate)
        receiver = threading.Thread(target=rt.receive_loop, args=(client,))
        receiver.start()
        rt.send_loop(conn)
        receiver.join(args.duration + 30)
        client.close()
        conn.close()
    finally:
        child.terminate()  # SIGTERM: the service stops cleanly and reports its counters
        stats = _child_stats(queue)
        child.join(10)
        plus.close()
    rtt = (rt.received - rt.sent)[~np.isnan(rt.received)] * 1e3
    lost = int(np.isnan(rt.received).sum())
    p50, p99 = percentiles(rtt)
    print(f"  p50 {p50:.3f} ms  p99 {p99:.3f} ms  max {np.max(rtt):.3f} ms  lost {lost}")
    if stats:
        print(f"  service: poses handled {stats['poses_handled']}, coalesced "
              f"{stats['poses_coalesced']}, last update {stats['last_update_ms']:.3f} ms")
    return p50, p99, lost


def _warm_up(conn: socket.socket, client: socket.socket, rest: np.ndarray) -> None:
    """Send the rest pose (auto rest pose) and wait for its POINT."""
    conn.sendall(encode_transform(PROBE_DEVICE, rest, TS_BASE - 1 + 0.5))
    reader = MessageReader()
    client.settimeout(30)
    while True:
        data = client.recv(1 << 16)
        if not data:
            raise SystemExit("service closed the client connection during warm-up")
        if any(getattr(m, "device", None) == POINT_DEVICE for m in reader.feed(data)):
            return


def _child_stats(queue) -> dict | None:
    try:
        while True:
            kind, value = queue.get(timeout=10)
            if kind == "stats":
                return value
    except Exception:
        return None


# ------------------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case_dir", nargs="?", default=None, help="case folder with a trained model")
    p.add_argument("--duration", type=float, default=60.0, help="round-trip duration, s")
    p.add_argument("--quick", action="store_true", help="5 s round trip")
    p.add_argument("--rate", type=float, default=100.0, help="probe pose rate, Hz")
    p.add_argument("--updates", type=int, default=2000, help="poses timed for update()")
    p.add_argument("--poses", default=None, help="poses CSV (frame, sequence, m00 ... m23)")
    p.add_argument("--push-mm", type=float, default=8.0, help="synthetic push depth, mm")
    p.add_argument("--lesion", type=int, default=1,
                   help="synthetic pushes over the case's lesion of this index (1: the first)")
    p.add_argument("--follow", action="store_true",
                   help="time update() again with [tracker] contact_follows_pose on")
    p.add_argument("--result-name", default="tracking-latency",
                   help="result file name under benchmarks/results (without .json)")
    args = p.parse_args(argv)
    if args.follow and args.case_dir is None:
        p.error("--follow needs CASE_DIR")
    if args.quick:
        args.duration = 5.0
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    csv_poses = read_poses_csv(args.poses) if args.poses else None

    def poses_for(tracker, n: int) -> np.ndarray:
        if csv_poses is not None:
            return csv_poses[np.arange(n) % len(csv_poses)]
        return synthetic_poses(rest_pose_of(tracker, args.lesion - 1), n, args.rate,
                               args.push_mm)

    upd50, upd99 = bench_update(args, poses_for)
    follow = bench_follow(args, poses_for) if args.follow else None
    fem = bench_fem(args, poses_for)
    rtt50, rtt99, lost = bench_round_trip(args, poses_for)
    extra = ("" if follow is None else
             f" follow_p50_ms={follow[0]:.3f} follow_p99_ms={follow[1]:.3f} "
             f"follow_held={follow[2]}")
    print(f"RESULT update_p50_ms={upd50:.3f} update_p99_ms={upd99:.3f} rtt_p50_ms={rtt50:.3f} "
          f"rtt_p99_ms={rtt99:.3f} lost={lost} fem_update_ms={fem:.1f}{extra}")
    if args.case_dir and not args.quick:
        write_result(args.result_name, {
            "update_p50_ms": upd50, "update_p99_ms": upd99, "rtt_p50_ms": rtt50,
            "rtt_p99_ms": rtt99, "lost": lost, "fem_update_ms": fem}, case=str(args.case_dir),
            speed_probes=speed_probes())  # after the timings: it would load the machine
    return 0


if __name__ == "__main__":
    sys.exit(main())
