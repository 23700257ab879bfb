"""OpenIGTLink for ``heartreg track`` (pyigtl 0.3): the server Slicer connects to and its rate limit,
a client that loses no message, and the pose stream from a tracker server.

Formats and device names: ``docs/formats.md`` (*Track log and OpenIGTLink
messages*).  pyigtl 0.3.4 packs POLYDATA but cannot unpack it, keeps only the
latest incoming message per device, installs its own SIGINT/SIGTERM handlers
in its server and drops the oldest queued message beyond 100: this module
works around each (see the functions).
"""

from __future__ import annotations

import bisect
import collections
import signal
import struct
import time
from collections.abc import Iterator

import numpy as np

from hrcore.errors import HeartregError
from registration.session_format import MAX_FRAME_GAP, MIN_TRACKER_RATE_HZ

__all__ = [
    "DEVICE_MODEL",
    "DEVICE_PROBE",
    "DEVICE_ROBOT",
    "DEVICE_SIGNALS",
    "DEVICE_STATUS",
    "DEVICE_TRANSFORM",
    "IgtlError",
    "IgtlSink",
    "RateLimiter",
    "igtl_client_chunks",
    "lossless_client",
    "unpack_polydata",
]

DEVICE_MODEL, DEVICE_TRANSFORM, DEVICE_STATUS = "HeartModel", "RobotToRAS", "RobotStatus"


class IgtlError(HeartregError, ValueError):
    """An OpenIGTLink port or peer that cannot be used."""


class IgtlSink:
    """An OpenIGTLink server (pyigtl) that Slicer's OpenIGTLinkIF connects to.

    pyigtl 0.3 has a ``PolyDataMessage`` that packs points and polygons
    (it cannot unpack one: a pyigtl *client* drops POLYDATA messages, see
    :func:`unpack_polydata`).  The model goes once per (re)connection.

    Parameters
    ----------
    port : int
        TCP port; 0 picks a free one (``port`` tells which).
    vertices_ras : (V, 3) float, mm
    faces : (F, 3) int
    """

    def __init__(self, port: int, vertices_ras, faces):
        import pyigtl

        self._pyigtl = pyigtl
        previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            self._server = pyigtl.OpenIGTLinkServer(port=int(port), local_server=True)
        except OSError as exc:
            raise IgtlError(f"--igtl-port {port}: cannot listen ({exc}); choose another port") from None
        finally:
            for s, h in previous.items():  # pyigtl installs its own; Ctrl-C stays ours
                if signal.getsignal(s) is not h:
                    signal.signal(s, h)
        self.port = int(self._server.server_address[1])
        # pyigtl serves one client at a time: the next one's handler starts as soon as the last one's ends, too
        # soon for a change of ``connected`` to be seen; a count of handlers tells each new connection
        self._server.connections = 0
        self._server.RequestHandlerClass = _counting_handler(pyigtl)
        self._seen = 0
        faces = np.asarray(faces, dtype=np.uint32)
        polys = np.concatenate([np.full((faces.shape[0], 1), 3, np.uint32), faces], axis=1).ravel()
        self._model = pyigtl.PolyDataMessage(points=np.asarray(vertices_ras, dtype=np.float32),
                                             polygons=polys, device_name=DEVICE_MODEL)
        self._was_connected = False
        self.models_sent = 0

    @property
    def connected(self) -> bool:
        return bool(self._server.is_connected())

    def wait_for_client(self, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        while not self.connected and time.monotonic() < end:
            time.sleep(0.005)
        return self.connected

    def poll(self) -> bool:
        """Send the model on a new connection; True while a client is connected."""
        now = self.connected
        count = self._server.connections
        if now and (not self._was_connected or count != self._seen):
            self._server.send_message(self._model, wait=False)
            self.models_sent += 1
            self._seen = count
        self._was_connected = now
        return now

    def send(self, time_s: float, T_ras_from_robot, text: str) -> None:
        """Queue one sample's TRANSFORM and STRING (timestamp: the sample time).

        pyigtl's queue holds 100 messages and drops the oldest beyond; when it
        is 80 % full this waits (at most 0.5 s) for it to drain instead.
        """
        pyigtl = self._pyigtl
        server = self._server
        if len(server.outgoing_messages) > 80:
            end = time.monotonic() + 0.5
            while len(server.outgoing_messages) > 20 and time.monotonic() < end and self.connected:
                time.sleep(0.0005)
        self._server.send_message(pyigtl.TransformMessage(T_ras_from_robot, timestamp=time_s,
                                                          device_name=DEVICE_TRANSFORM), wait=False)
        self._server.send_message(pyigtl.StringMessage(text, timestamp=time_s, device_name=DEVICE_STATUS),
                                  wait=False)

    def flush(self, timeout_s: float = 2.0) -> None:
        """Wait (bounded) until the queued messages have gone out."""
        end = time.monotonic() + timeout_s
        while self.connected and time.monotonic() < end:
            with self._server.lock_outgoing_messages:
                if not self._server.outgoing_messages:
                    return
            time.sleep(0.002)

    def close(self) -> None:
        self._server.communication_thread_stop_requested = True
        self._server.shutdown()
        self._server.server_close()


class RateLimiter:
    """At most ``max_hz`` events per second of the given clock; the rest are
    dropped quietly and counted (``dropped``)."""

    def __init__(self, max_hz: float | None, *, clock=time.monotonic):
        if max_hz is not None and not max_hz > 0:
            raise ValueError(f"max_hz must be positive or None, got {max_hz!r}")
        self._interval = 0.0 if max_hz is None else 1.0 / float(max_hz)
        self._clock = clock
        self._next = -np.inf
        self.passed = 0
        self.dropped = 0

    def allow(self) -> bool:
        now = self._clock()
        if now >= self._next:
            # the budget follows the clock; a late event does not earn a burst
            self._next = max(self._next + self._interval, now) if np.isfinite(self._next) else now + self._interval
            self.passed += 1
            return True
        self.dropped += 1
        return False


def _counting_handler(pyigtl):
    """A request handler for pyigtl's server that counts the connections it serves and lets a client go
    quietly: pyigtl's own prints two tracebacks on stderr whenever a client leaves (a reset, a broken pipe),
    in the middle of a live session's output."""
    import logging

    from pyigtl.comm import TCPRequestHandler

    log = logging.getLogger(__name__)

    class _Counting(TCPRequestHandler):
        def handle(self):
            server = self.server
            server.connections += 1
            server._connected = True
            self.request.settimeout(0.01)
            try:
                while not server.communication_thread_stop_requested:
                    while server._receive_message_from_socket(self.request):
                        if server.communication_thread_stop_requested:
                            break
                    while server._send_queued_message_from_socket(self.request):
                        pass
            except OSError as exc:  # the client left
                log.info("OpenIGTLink client gone (%s)", exc)
            except Exception as exc:  # noqa: BLE001 - a peer's garbage must not stop the server
                log.warning("OpenIGTLink connection dropped: %s", exc)
            finally:
                server._communication_error_occurred()

    return _Counting


def unpack_polydata(content: bytes):
    """Points (V, 3) float32 and triangles (F, 3) of a POLYDATA body (no attributes).

    pyigtl 0.3 cannot unpack POLYDATA; this reads what :class:`IgtlSink` sends
    (OpenIGTLink v2 POLYDATA: ten uint32 counts, float32 points, uint32 cells).
    """
    head = np.frombuffer(content[:40], dtype=">u4")
    n_points = int(head[0])
    sizes = head[[2, 4, 6, 8]]
    off = 40
    points = np.frombuffer(content[off:off + 12 * n_points], dtype=">f4").reshape(-1, 3)
    off += 12 * n_points + int(sizes[0]) + int(sizes[1])
    polys = np.frombuffer(content[off:off + int(sizes[2])], dtype=">u4").reshape(-1, 4)
    if np.any(polys[:, 0] != 3):
        raise ValueError("POLYDATA polygons are not all triangles")
    return points.astype(np.float32), polys[:, 1:].astype(np.int64)


#: device names of an OpenIGTLink pose stream (PLUS's naming).
DEVICE_ROBOT, DEVICE_PROBE, DEVICE_SIGNALS = "RobotToTracker", "ProbeToTracker", "Signals"


#: messages ``igtl_client_chunks`` lets wait (1000 samples: 1 s of a 1 kHz robot); beyond, it reads no more and
#: TCP holds the server back, so a server faster than the tracker neither fills memory nor lets the map lag on.
MAX_QUEUED = 3000
#: the largest message body read (a POLYDATA of a 1M-face model is ~30 MB); a header claiming more is garbage.
MAX_BODY_BYTES = 256 << 20


def lossless_client(host: str, port: int, *, max_queued: int | None = None):
    """A pyigtl client that keeps every message (pyigtl keeps only the latest
    per device); POLYDATA bodies are kept raw (pyigtl 0.3 cannot unpack them:
    read them with :func:`unpack_polydata`).

    Its reader replaces pyigtl's, which (0.3.2) hung ``stop()`` while the server streamed without a 10 ms pause
    (Ctrl-C of a live run never ended), printed two tracebacks and dropped the connection on one malformed
    message, and never saw a server that closed the connection (it spun on the dead socket, never reconnecting).
    Here a malformed body is dropped and counted, a closed or reset connection or a garbage header closes the
    socket (pyigtl reconnects every 10 ms), and a stop request ends the reading at once.

    Returns
    -------
    client, messages
        ``messages`` is a ``collections.deque`` the client appends to; ``client.problems`` counts what was
        dropped (``{reason: n}``, filled by the client's thread).
    """
    import collections
    import logging
    import socket

    import pyigtl
    from pyigtl import messages as pm

    received = collections.deque()
    log = logging.getLogger(__name__)
    head = pyigtl.MessageBase.IGTL_HEADER_SIZE

    class _RawPolyData(pyigtl.MessageBase):
        def __init__(self):
            super().__init__()
            self._message_type = "POLYDATA"
            self.content = b""

        def _unpack_content(self, content):
            self.content = bytes(content)

    class _Client(pyigtl.OpenIGTLinkClient):
        def _problem(self, why):
            self.problems[why] = self.problems.get(why, 0) + 1

        def _lost(self, ssocket, why):
            log.info("OpenIGTLink server %s:%s: %s", self.host, self.port, why)
            self._problem(why)
            ssocket.close()
            self.socket, self._connected, self._buffer = None, False, bytearray()  # pyigtl's loop reconnects
            return False

        def _receive_message_from_socket(self, ssocket):
            if self.communication_thread_stop_requested:
                return False
            if max_queued is not None and len(received) >= max_queued:
                time.sleep(0.001)  # the reader is behind: the server waits (every sample is needed, in order)
                return False
            try:
                data = ssocket.recv(1 << 16)
            except socket.timeout:
                return False
            except OSError as exc:
                return self._lost(ssocket, f"connection lost ({exc.strerror or exc}), reconnecting")
            if not data:
                return self._lost(ssocket, "the server closed the connection, reconnecting")
            buf = self._buffer
            buf += data  # a bytearray: a large body (the model's POLYDATA) arrives without quadratic copies
            at = 0
            while len(buf) - at >= head:
                try:
                    fields = pyigtl.MessageBase.parse_header(bytes(buf[at:at + head]))
                except (ValueError, struct.error):  # not UTF-8 names: not OpenIGTLink, or out of step
                    fields = None
                if fields is None or int(fields["body_size"]) > MAX_BODY_BYTES:  # the messages before it count
                    return self._lost(ssocket, "a malformed message header, reconnecting")
                size = int(fields["body_size"])
                if len(buf) - at < head + size:
                    break
                body = bytes(buf[at + head:at + head + size])
                at += head + size
                kind = fields["message_type"]
                message = _RawPolyData() if kind == "POLYDATA" else pm.MessageBase.create_message(kind)
                if message is None:
                    continue  # a type this reader does not know (STATUS, ...): ignored, as OpenIGTLink says
                try:
                    message.unpack(fields, body)
                except Exception:  # noqa: BLE001 - a peer's malformed body (pyigtl raises struct, value errors)
                    self._problem(f"a malformed {kind} message ({fields['device_name']}), dropped")
                    continue
                received.append(message)
            del buf[:at]
            return True

    client = _Client(host=host, port=int(port), start_now=False)
    client.problems, client._buffer = {}, bytearray()
    client.start()
    return client, received


def _signals(text: str):
    """The three finite numbers of a ``Signals`` string, or None."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        return None
    return values if len(values) == 3 and all(np.isfinite(values)) else None


#: a ``Signals`` sample waits for the tracker frame after it at most this long (s, by the later samples' times);
#: the stream's end (``idle_timeout_s``) ends every wait.
MAX_WAIT_S = 0.25
#: tracker frames (and transforms waiting for their frame's other tool) kept when no sample takes them.
MAX_FRAMES = 64
#: the poses of a sample with no frame close enough around it (a tracker dropout, before the first frame, frames
#: too late): the robot not seen, logged 'tracker', its signals still feeding the phases (skipped, a dropout over
#: a tenth of a second restarted the phases: seconds with nothing placed)
NOT_SEEN = (np.full((4, 4), np.nan), np.eye(4))
#: why a sample is skipped: the stream ended while it waited for the frame after it.
SKIP_ENDED = "the stream ended before the tracker frame after the sample"


def _pose_at(frames: list, steps, t: float):
    """The poses ``(T_tracker_from_robot, T_tracker_from_probe)`` of a sample at ``t`` from the tracker frames
    ``(time, robot, probe)`` (time-ordered): the frame at ``t`` as received, else the relative pose interpolated
    between the frames around ``t`` (with an identity probe: the same pose relative to the probe); None while no
    frame after ``t`` has come; :data:`NOT_SEEN` when there is none before it or those frames are more than
    ``MAX_FRAME_GAP`` median steps apart (``steps``: the last frame steps)."""
    times = [f[0] for f in frames]
    k = bisect.bisect_right(times, t)  # frames[:k] are at or before t
    if k and times[k - 1] == t:
        return frames[k - 1][1:]
    if k == len(frames):
        return None
    # the gap a lost frame makes, by the tracker's median step (a slowest tracker's until three steps are known)
    step = float(np.median(steps)) if len(steps) >= 3 else 1.0 / MIN_TRACKER_RATE_HZ
    if k == 0 or times[k] - times[k - 1] > MAX_FRAME_GAP * step:
        return NOT_SEEN
    return _between(frames[k - 1], frames[k], t), np.eye(4)


def _between(f0, f1, t: float) -> np.ndarray:
    """``T_probe_from_robot`` at ``t`` between two frames, as the PLUS reader interpolates (translation linear,
    rotation along the shortest arc); NaN when a frame's pose is no rigid transform (the sample is 'tracker')."""
    from hrcore.geometry import interpolate_poses, is_rigid
    from registration.plus import RIGID_TOL

    if not is_rigid(np.array([f0[1], f0[2], f1[1], f1[2]]), tol=RIGID_TOL).all():
        return np.full((4, 4), np.nan)
    rel = np.tile(np.eye(4), (2, 1, 1))
    for T, (_, r, p) in zip(rel, (f0, f1)):
        T[:3, :3], T[:3, 3] = p[:3, :3].T @ r[:3, :3], p[:3, :3].T @ (r[:3, 3] - p[:3, 3])
    return interpolate_poses(rel[:1], rel[1:], [(t - f0[0]) / (f1[0] - f0[0])])[0]


def igtl_client_chunks(host: str, port: int, *, idle_timeout_s: float = 5.0, skipped: dict | None = None,
                       problems: dict | None = None) -> Iterator:
    """Samples from an OpenIGTLink server (e.g. PlusServer), one chunk per sample, in time order.

    A tracker frame is a ``TRANSFORM`` ``RobotToTracker`` and a ``TRANSFORM`` ``ProbeToTracker`` with the same
    timestamp; a sample is a ``STRING`` ``Signals`` (``"ecg_mv,flow_insp_lpm,flow_exp_lpm"``: three finite
    numbers) at its timestamp (the sample time, s, on the tracker's clock).  A sample takes the frame with its
    timestamp if there is one (a server sending all three per sample), else the pose interpolated between the
    frames around it (a tracker at its own rate): it waits for the frame after it, at most ``MAX_WAIT_S`` of
    the samples' time.  A sample between frames more than ``MAX_FRAME_GAP`` median steps apart, before the
    first frame or whose frame after it is later than that wait comes with the robot not seen
    (:data:`NOT_SEEN`: logged 'tracker', its signals still feed the phases).  A sample with bad signals, not
    later than the one before, or still waiting when the stream ends is skipped, counted by reason in
    ``skipped``; one bad sample does not end a live run.  The stream ends after ``idle_timeout_s`` without
    a message; a server that never answers is an :class:`IgtlError`.  A malformed message is dropped, a
    connection the server closed is opened again (:func:`lossless_client`): each counted by reason in
    ``problems`` when the stream ends.
    """
    from heartreg.track import chunks_from_samples

    skipped = {} if skipped is None else skipped

    def skip(why):
        skipped[why] = skipped.get(why, 0) + 1

    client, received = lossless_client(host, port, max_queued=MAX_QUEUED)
    parts: dict[float, dict] = {}  # a frame's transforms waiting for its other tool
    frames: list = []  # (time, robot, probe), time-ordered, from the last one at or before the last sample
    steps = collections.deque(maxlen=MAX_FRAMES)  # the last frame steps
    waiting = collections.deque()  # samples (time, signals) waiting for the frame after them, time-ordered
    last = time.monotonic()
    latest = -np.inf
    heard = False
    try:
        while True:
            if not received:
                if time.monotonic() - last > idle_timeout_s:
                    if not heard:
                        state = "connected but sent nothing" if client.is_connected() else "no connection"
                        raise IgtlError(f"--igtl-in {host}:{port}: {state} within {idle_timeout_s:g} s "
                                        "(--idle-timeout); is the tracker's OpenIGTLink server running there?")
                    for _ in range(len(waiting)):
                        skip(SKIP_ENDED)
                    return
                time.sleep(0.001)
                continue
            last, heard = time.monotonic(), True
            msg = received.popleft()
            key = round(float(msg.timestamp), 6)
            if msg.device_name in (DEVICE_ROBOT, DEVICE_PROBE) and msg.message_type == "TRANSFORM":
                slot = parts.setdefault(key, {})
                slot[msg.device_name] = np.asarray(msg.matrix, dtype=float)
                if len(slot) == 2:
                    for old in [k for k in parts if k <= key]:
                        parts.pop(old)  # an incomplete earlier frame will not complete now
                    # in time order, wherever it falls: one frame stamped far ahead (a glitch) blocks no later one
                    at = bisect.bisect_left([f[0] for f in frames], key)
                    if at == len(frames) or frames[at][0] != key:
                        if at:
                            steps.append(key - frames[at - 1][0])
                        frames.insert(at, (key, slot[DEVICE_ROBOT], slot[DEVICE_PROBE]))
                        del frames[:-MAX_FRAMES]
                while len(parts) > MAX_FRAMES:
                    parts.pop(min(parts))
            elif msg.device_name == DEVICE_SIGNALS and msg.message_type == "STRING":
                values = _signals(msg.string)
                if values is None:
                    skip("Signals not three finite numbers (ecg_mv,flow_insp_lpm,flow_exp_lpm)")
                    continue
                if not key > latest:
                    skip("timestamp not later than the sample before")
                    continue
                latest = key
                waiting.append((key, values))
            while waiting:
                t, values = waiting[0]
                pose = _pose_at(frames, steps, t)
                if pose is None or pose is NOT_SEEN:
                    if latest - t <= MAX_WAIT_S:
                        break  # the frame after it (or a nearer one, out of order) may yet come
                    pose = NOT_SEEN
                waiting.popleft()
                while len(frames) > 1 and frames[1][0] <= t:
                    frames.pop(0)  # the next sample is later: only the last frame at or before t may serve it
                yield next(chunks_from_samples([(t, *pose, pose is not NOT_SEEN, *values)]))
    finally:
        client.stop()
        if problems is not None:
            for why, k in client.problems.items():
                problems[why] = problems.get(why, 0) + k
