"""``--igtl-in`` against a robot's OpenIGTLink server that misbehaves the way real ones do (loopback only, every
server and wait bounded in time): one that streams without a pause, one that sends a malformed message, one that
closes the connection and takes the next.  No model needed: the pose stream itself is checked."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pyigtl

from heartreg.igtl import DEVICE_PROBE, DEVICE_ROBOT, DEVICE_SIGNALS, igtl_client_chunks


def _sample(i: int) -> bytes:
    t = 1000.0 + 0.01 * i
    robot = np.eye(4)
    robot[:3, 3] = [i, 2.0, 3.0]
    return b"".join(m.pack() for m in (
        pyigtl.TransformMessage(robot, timestamp=t, device_name=DEVICE_ROBOT),
        pyigtl.TransformMessage(np.eye(4), timestamp=t, device_name=DEVICE_PROBE),
        pyigtl.StringMessage("0.1,1.0,0.5", timestamp=t, device_name=DEVICE_SIGNALS)))


def _raw(kind: str, device: str, body: bytes) -> bytes:
    from pyigtl.messages import CRC64

    return struct.pack(">H12s20sIIQQ", 1, kind.encode(), device.encode(), 1000, 0, len(body), CRC64(body)) + body


def _serve(script):
    """A server on 127.0.0.1 (a free port) running ``script(accept)`` in a thread; ``accept()`` gives the next
    connection (5 s at most)."""
    ls = socket.socket()
    ls.bind(("127.0.0.1", 0))
    ls.listen(1)
    ls.settimeout(5.0)

    def accept():
        conn, _ = ls.accept()
        conn.settimeout(5.0)
        return conn

    def run():
        try:
            script(accept)
        except OSError:
            pass  # the client left
        finally:
            ls.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return ls.getsockname()[1], thread


def _collect(port, **kw):
    problems: dict = {}
    x = [float(c.T_tracker_from_robot[0, 0, 3]) for c in igtl_client_chunks("127.0.0.1", port, problems=problems,
                                                                             **kw)]
    return x, problems


def _served(script, *, idle_timeout_s, join_s):
    """What the client takes from a loopback server running ``script``: (x of each sample, problems)."""
    port, server = _serve(script)
    x, problems = _collect(port, idle_timeout_s=idle_timeout_s)
    server.join(timeout=join_s)
    return x, problems


def test_ctrl_c_ends_a_live_run_while_the_robot_streams_without_a_pause():
    """pyigtl's reader (0.3.2) reads on while messages come less than 10 ms apart and only then looks at its stop
    flag: closing the stream (Ctrl-C) hung as long as a robot streamed at 1 kHz (measured: still running 20 s
    after SIGINT, the log unwritten).  Now the stream closes at once."""
    stop = threading.Event()

    def script(accept):
        conn = accept()
        i, end = 0, time.monotonic() + 10.0
        while not stop.is_set() and time.monotonic() < end:
            conn.sendall(_sample(i))
            i += 1
            time.sleep(0.0005)
        conn.close()

    port, server = _serve(script)
    closed: list = []

    def consume():
        chunks = igtl_client_chunks("127.0.0.1", port, idle_timeout_s=3.0)
        for k, _ in enumerate(chunks):
            if k == 20:
                break
        t0 = time.monotonic()
        chunks.close()  # what Ctrl-C does to the source (run_track's for loop ends)
        closed.append(time.monotonic() - t0)

    worker = threading.Thread(target=consume, daemon=True)
    worker.start()
    worker.join(timeout=6.0)
    hung = worker.is_alive()
    stop.set()
    server.join(timeout=11.0)
    assert not hung and closed and closed[0] < 1.0, f"closing the stream took {closed or 'more than 6 s'}"


def test_a_malformed_message_is_dropped_and_the_stream_goes_on(capfd):
    """A truncated TRANSFORM body made pyigtl print two tracebacks, drop the connection and lose every sample
    after it (a robot's server that accepts once: 31 of 50 samples arrived after the second).  Now it is
    dropped and counted, a message of an unknown type is ignored, and every sample arrives."""
    def script(accept):
        conn = accept()
        for i in range(50):
            conn.sendall(_sample(i))
            if i in (10, 30):
                conn.sendall(_raw("TRANSFORM", DEVICE_ROBOT, b"\0" * 10) + _raw("FOOBAR", "Robot", b"xyz"))
        time.sleep(2.0)
        conn.close()

    x, problems = _served(script, idle_timeout_s=1.0, join_s=5.0)
    assert x == [float(i) for i in range(50)]
    assert problems == {f"a malformed TRANSFORM message ({DEVICE_ROBOT}), dropped": 2}
    assert "Traceback" not in capfd.readouterr().err


def test_a_server_that_closes_the_connection_is_reconnected():
    """pyigtl never saw a server close the connection (it read nothing forever, at full CPU): a robot's server
    restarted mid-run lost the rest of the stream (30 of 60 samples).  Now the client connects again."""
    def script(accept):
        for part in range(2):
            conn = accept()
            for i in range(30 * part, 30 * part + 30):
                conn.sendall(_sample(i))
            time.sleep(0.3)
            conn.close()

    x, problems = _served(script, idle_timeout_s=1.5, join_s=10.0)
    assert x == [float(i) for i in range(60)]
    assert problems.get("the server closed the connection, reconnecting", 0) >= 1, problems


def test_a_server_faster_than_the_tracker_is_held_back_not_queued():
    """The client read everything a server sent into memory: a robot streaming flat out while ``heartreg track``
    processed ~1300 samples/s grew the process by 26 MB/s (1.8 GB after 60 s; the map lagging ever more).  Now
    no more is read while ``max_queued`` messages wait: TCP holds the server back, and reading resumes."""
    from heartreg.igtl import MAX_QUEUED, lossless_client

    assert 0 < MAX_QUEUED <= 10000
    sent = [0]

    def script(accept):
        conn = accept()
        conn.settimeout(0.5)  # held back for 0.5 s: the server gives up (bounded)
        i, end = 0, time.monotonic() + 3.0
        try:
            while time.monotonic() < end:
                conn.sendall(_sample(i))
                i += 1
        except socket.timeout:
            pass
        sent[0] = i
        time.sleep(1.0)
        conn.close()

    port, server = _serve(script)
    client, received = lossless_client("127.0.0.1", port, max_queued=300)
    try:
        time.sleep(1.5)
        waiting = len(received)
        for _ in range(200):
            received.popleft()
        time.sleep(0.2)
        resumed = len(received)
    finally:
        client.stop()
        server.join(timeout=6.0)
    assert 300 <= waiting < 1100, waiting  # one 64 kB read past the limit at most (~700 messages)
    assert resumed >= 300, resumed  # reading resumed once the consumer took some
    assert sent[0] < 20000, sent  # the server was held back (flat out it sends ~100 000 samples in 3 s)
