"""Bus reading of the HIL harness: the python-can monitor thread that records every frame
and drives the brake-controller emulator (hilemu) live, waits for frames in bus time, and
sends the marker frames that sync it.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import can

from hilemu import BrakeController, Frame
from hilrig import RigError

MARKER_ID = 0x7FF  # harness marker frames (lowest priority ID, ignored by the checks)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # root may exceed rmem_max
LAG_MAX_S = 10.0  # how far the bus monitor may fall behind the bus before a wait gives up


CAN_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: id, length, pad and reserved, data


def next_frame(iface: str, can_id: int, timeout: float) -> tuple[float, bytes] | None:
    """The next frame of the standard CAN ID ``can_id`` on the bus from now on, read from a raw
    socket of its own by the calling thread (the wall time it was read, its data), or None
    within ``timeout`` s. Not through the bus monitor: under a loaded TCG guest that thread fell
    seconds behind the bus, and a row that waited for the daemon's next periodic frame through
    it before its last packet waited 100 to 800 ms (every dead-man sample spoiled)."""
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    try:
        mask = socket.CAN_SFF_MASK | socket.CAN_EFF_FLAG | socket.CAN_RTR_FLAG
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER,
                        struct.pack("=II", can_id, mask))
        sock.bind((iface,))
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            sock.settimeout(left)
            try:
                raw = sock.recv(CAN_FRAME.size)
            except TimeoutError:
                return None
            if len(raw) == CAN_FRAME.size:
                _, n, data = CAN_FRAME.unpack(raw)
                return time.time(), data[:n]
        return None
    finally:
        sock.close()


@dataclass(frozen=True, slots=True)
class BusError:
    ts: float
    text: str


class BusMonitor:
    """python-can receiver thread: records every frame and drives the brake controller
    emulator in real time (its 50 ms watchdog is checked at least every millisecond)."""

    def __init__(self, iface: str) -> None:
        self.iface = iface
        self.bus = can.Bus(interface="socketcan", channel=iface, receive_own_messages=False)
        # A large receive queue: under load this thread may fall seconds behind, and a frame
        # lost here would look like a frame the daemon never sent (candump would disagree).
        sock = getattr(self.bus, "socket", None)
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 8 << 20)
            except OSError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.frames: list[Frame] = []
        self.errors: list[BusError] = []
        self.ctl = BrakeController()
        self._tx: can.BusABC | None = None  # sends the marker frames
        self.max_lag = 0.0  # seconds this thread read a frame after its kernel timestamp
        self.max_lag_at = 0.0
        self.lag_giveups = 0  # waits given up because this thread was LAG_MAX_S behind
        self.cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bus-monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            # Sleep in recv() until the next frame or the emulator's watchdog deadline.
            with self.cond:
                last, tripped = self.ctl.last_good, self.ctl.tripped
            wait = 0.05
            if last is not None and not tripped:
                wait = min(wait, max(0.0, last + self.ctl.silence_s - time.time()))
            msg = self._recv(wait)
            now = None
            if msg is None:
                # Nothing arrived until ``now``; a frame that slipped in meanwhile still counts
                # by its kernel timestamp, so look once more before declaring silence.
                now = time.time()
                msg = self._recv(0.0)
            batch = [] if msg is None else [msg]
            # Behind the bus (a loaded host): take what is queued in one go, one lock and one
            # wake-up of the waiting scenario for many frames, to catch up sooner.
            while batch and len(batch) < 64 and time.time() - batch[-1].timestamp > 0.05:
                more = self._recv(0.0)
                if more is None:
                    break
                batch.append(more)
            with self.cond:
                for m in batch:
                    lag = time.time() - m.timestamp  # how far behind the bus this thread is
                    if lag > self.max_lag:
                        self.max_lag, self.max_lag_at = lag, m.timestamp
                    fr = Frame(m.timestamp, m.arbitration_id, bytes(m.data))
                    self.frames.append(fr)
                    self.ctl.on_frame(fr)
                if not batch and now is not None:
                    self.ctl.on_tick(now)
                self.cond.notify_all()

    def _recv(self, timeout: float) -> can.Message | None:
        try:
            msg = self.bus.recv(timeout=timeout)
        except can.CanError as exc:  # ENETDOWN once when the link goes down, ...
            with self.cond:
                self.errors.append(BusError(time.time(), str(exc)))
            return None
        if msg is None or msg.is_error_frame or msg.is_remote_frame:
            return None
        return msg

    def index(self) -> int:
        with self.cond:
            return len(self.frames)

    def since(self, start: int) -> list[Frame]:
        with self.cond:
            return self.frames[start:]

    def window(self, t0: float, t1: float) -> list[Frame]:
        with self.cond:
            return [f for f in self.frames if t0 <= f.ts <= t1]

    def wait_for(self, pred: Callable[[Frame], bool], start: int,
                 timeout: float) -> Frame | None:
        """First frame from index ``start`` on that satisfies ``pred``, if one is on the bus
        within ``timeout`` seconds from now. "Within" is bus time (kernel timestamps): when
        this thread lags behind the bus (a loaded host), it is waited for, up to LAG_MAX_S
        more, so that a frame that came in time is never missed for being read late."""
        t_bus_end = time.time() + timeout
        end = time.monotonic() + timeout + LAG_MAX_S
        i = start
        with self.cond:
            while True:
                while i < len(self.frames):
                    if pred(self.frames[i]):
                        return self.frames[i]
                    i += 1
                if self.frames and self.frames[-1].ts > t_bus_end:
                    return None  # read past the deadline: none came in time
                left = end - time.monotonic()
                if left <= 0:
                    self.lag_giveups += 1  # not a finding: this thread fell too far behind
                    return None
                self.cond.wait(min(left, 0.05))

    def marker(self, text: bytes) -> Frame:
        """Send a marker frame from a separate socket and wait until it is seen."""
        start = self.index()
        msg = can.Message(arbitration_id=MARKER_ID, data=text[:8], is_extended_id=False)
        for attempt in range(2):
            if self._tx is None:
                self._tx = can.Bus(interface="socketcan", channel=self.iface)
            try:
                self._tx.send(msg)
                break
            except can.CanError:
                # A socket keeps an error of its interface going down (ENETDOWN) for its next
                # send: a fresh socket then.
                self._tx.shutdown()
                self._tx = None
                if attempt:
                    raise
        fr = self.wait_for(lambda f: f.can_id == MARKER_ID and f.data == text[:8], start, 2.0)
        if fr is None:
            raise RigError(f"marker frame {text!r} was not received back on {self.iface}")
        return fr

    def sync(self) -> None:
        """Return once this thread has read every frame sent before now (a marker frame
        behind them: a socket's queue keeps the order)."""
        self.marker(b"HILSYNC")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.shutdown()
        if self._tx is not None:
            self._tx.shutdown()
