"""The baseline: the estop rules as a team would write them without estopd.

A straightforward Python asyncio daemon with the same options and outputs as estopd (section 5
of PROTOCOL.md), so ``bench/stop_latency.py`` measures both identically:

- boots STOPPED (reason boot); STOPPED is latched; RELEASE needs a live link (a valid packet
  less than the timeout ago and >= 5 valid packets since the stop) and a neutral last packet;
- a UDP ``DatagramProtocol`` validates control packets and records the time of the latest one;
  a 48-byte request frame there is a stop or lift datagram (version 3: LIFT stops with reason
  lift, whatever its tag);
- the TCP stop channel is an ``asyncio.start_server`` handler reading 16-byte frames (STOP,
  LIFT, STATUS, RELEASE);
- one periodic task (``asyncio.sleep`` of the check period, 10 ms = the brake period) checks
  the watchdog and sends ESTOP_BRAKE every 10 ms and ESTOP_STATUS every 100 ms; state changes
  send a brake frame at once. With ``--slow-ms S`` below the timeout it is a two-stage unit:
  SLOWING (brake_request 2 at ``--slow-level``) after S of silence, back to ARMED after 3
  valid packets, STOPPED at the timeout.

That periodic check is the usual design and the point of the comparison: a timeout is only
noticed at the next tick (plus the event loop's scheduling delay), whereas the spec asks for
the stop at the deadline itself. Frames go to a can-utils log (``--can-log PATH|-``, default
stdout) stamped with time.time() when sent; log lines go to stderr in estopd's text format.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import socket
import sys
import time
from typing import TextIO

from estop.protocol import auth, can, canlog, tcp, udp

STOPPED, ARMED, SLOWING = can.State.STOPPED, can.State.ARMED, can.State.SLOWING
R_NONE, R_BOOT = can.Reason.NONE, can.Reason.BOOT
R_TCP_STOP, R_UDP_TIMEOUT, R_LIFT = can.Reason.TCP_STOP, can.Reason.UDP_TIMEOUT, can.Reason.LIFT
RELEASE_PACKETS = 5
RESUME_PACKETS = 3  # valid packets that end SLOWING


def _sat(v: int, top: int = 255) -> int:
    return v if v < top else top


class Unit:
    """The watchdog state, the CAN output, and the periodic task."""

    def __init__(self, out: TextIO, timeout_s: float, stop_id: int, check_s: float,
                 slow_s: float | None = None, slow_level: int = can.DEFAULT_SLOW_LEVEL) -> None:
        self.out = out
        self.timeout_s = timeout_s
        self.slow_s = timeout_s if slow_s is None else slow_s
        self.slow_level = slow_level
        self.warn_s = int(self.slow_s * 1000) // 2 / 1000.0  # half S, whole ms (spec 3)
        self.resume_run = 0  # valid packets since SLOWING began
        self.stop_id = stop_id
        self.check_s = check_s
        self.state: int = STOPPED
        self.reason: int = R_BOOT
        self.last_valid = 0.0  # monotonic time of the latest valid packet (0: none)
        self.last_neutral = False
        self.valid_run = 0
        self.brake_counter = 0
        self.status_counter = 0
        self.n_valid = self.n_invalid = self.n_bad_crc = self.n_stops = self.n_slowdowns = 0
        self.next_brake = 0.0
        self.next_status = 0.0

    # -- output --------------------------------------------------------------------------
    def log(self, text: str) -> None:
        sys.stderr.write(f"baseline {time.monotonic():.6f} {text}\n")
        sys.stderr.flush()

    def _emit(self, can_id: int, data: bytes) -> None:
        canlog.write_record(self.out, canlog.CanLogRecord.at(time.time(), "estop", can_id, data))

    def flags(self) -> int:
        if self.state != STOPPED and time.monotonic() - self.last_valid >= self.warn_s:
            return 1
        return 0

    def send_brake(self) -> None:
        frame = can.BrakeFrame.for_state(self.state, self.reason, self.flags(),
                                         self.brake_counter, self.slow_level)
        self._emit(can.BRAKE_ID, frame.encode())
        self.brake_counter = (self.brake_counter + 1) % 15
        self.next_brake = time.monotonic() + 0.010

    def send_status(self) -> None:
        age = time.monotonic() - self.last_valid
        age_ms = int(age * 1000) if self.last_valid and age < self.timeout_s else 0xFFFF
        # counts per window (since the last STATUS); stops is a nibble since version 3
        frame = can.StatusFrame(_sat(self.n_valid), _sat(self.n_invalid), 0,  # no key: no auth
                                _sat(self.n_stops, can.NIBBLE_MAX), age_ms, self.status_counter,
                                _sat(self.n_slowdowns, can.NIBBLE_MAX))
        self._emit(can.STATUS_ID, frame.encode())
        self.n_valid = self.n_invalid = self.n_stops = self.n_slowdowns = 0
        self.status_counter = (self.status_counter + 1) % 15
        self.next_status = time.monotonic() + 0.100

    # -- rules -----------------------------------------------------------------------------
    def set_state(self, state: int, reason: int, src: str) -> None:
        old = self.state
        self.state, self.reason = state, reason
        self.log(f"state {can.state_name(old)}->{can.state_name(state)} "
                 f"reason={can.reason_name(reason)} src={src}")
        self.send_brake()

    def stop(self, reason: int, src: str) -> None:
        self.valid_run = 0
        if self.state != STOPPED:  # ARMED or SLOWING; a second stop keeps the first reason
            self.n_stops += 1
            self.set_state(STOPPED, reason, src)

    def link_live(self) -> bool:
        return (self.last_valid > 0 and time.monotonic() - self.last_valid < self.timeout_s
                and self.valid_run >= RELEASE_PACKETS)

    def on_udp(self, data: bytes, src: str) -> None:
        if len(data) == auth.REQUEST_SIZE and data[:4] == auth.REQUEST_MAGIC:
            self.on_stop_datagram(data, src)
            return
        try:
            pkt = udp.ControlPacket.decode(data)
        except udp.InvalidPacket:
            self.n_invalid += 1
            return
        self.n_valid += 1
        self.last_valid = time.monotonic()
        self.last_neutral = pkt.is_neutral
        self.valid_run += 1
        if self.state == SLOWING:
            self.resume_run += 1
            if self.resume_run >= RESUME_PACKETS:
                self.set_state(ARMED, R_NONE, src)

    def on_stop_datagram(self, data: bytes, src: str) -> None:
        """A stop or lift datagram: honoured whatever its tag (anyone may stop)."""
        try:
            kind = auth.AuthRequest.decode(data, None).kind(self.stop_id)
        except auth.AuthError:
            kind = "invalid"
        if kind == "stop":
            self.stop(R_TCP_STOP, src)
        elif kind == "lift":
            self.stop(R_LIFT, src)
        else:
            self.n_invalid += 1

    def on_request(self, req: tcp.Request, src: str) -> bytes:
        kind = req.kind(self.stop_id)
        nak = 0
        if kind == "stop":
            self.stop(R_TCP_STOP, src)
        elif kind == "lift":
            self.stop(R_LIFT, src)
        elif kind == "release":
            if self.state == STOPPED:
                if not self.link_live():
                    nak = tcp.NakCode.NO_LIVE_LINK
                elif not self.last_neutral:
                    nak = tcp.NakCode.NOT_NEUTRAL
                else:
                    self.set_state(ARMED, R_NONE, src)
        elif kind == "unknown":
            nak = tcp.NakCode.UNKNOWN_MSG_ID
        reply = tcp.Reply(nak == 0, req.seq, self.state, self.reason, self.flags(), nak)
        return reply.encode()

    async def periodic(self) -> None:
        self.send_brake()
        self.send_status()
        while True:
            await asyncio.sleep(self.check_s)
            now = time.monotonic()
            silent = now - self.last_valid
            if self.state != STOPPED and silent >= self.timeout_s:
                self.stop(R_UDP_TIMEOUT, "-")
            elif self.state == ARMED and self.slow_s < self.timeout_s and silent >= self.slow_s:
                self.n_slowdowns += 1
                self.resume_run = 0
                self.set_state(SLOWING, R_NONE, "-")
            if now >= self.next_brake:
                self.send_brake()
            if now >= self.next_status:
                self.send_status()


class UdpHandler(asyncio.DatagramProtocol):
    def __init__(self, unit: Unit) -> None:
        self.unit = unit

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.unit.on_udp(data, f"{addr[0]}:{addr[1]}")


async def tcp_client(unit: Unit, reader: asyncio.StreamReader,
                     writer: asyncio.StreamWriter) -> None:
    peer = writer.get_extra_info("peername")
    src = f"{peer[0]}:{peer[1]}" if peer else "?"
    sock = writer.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    try:
        while True:
            frame = await reader.readexactly(tcp.FRAME_SIZE)
            try:
                req = tcp.Request.decode(frame)
            except tcp.CrcMismatch:
                unit.n_bad_crc += 1
                unit.log(f"bad_crc src={src}")
                break
            writer.write(unit.on_request(req, src))
    except (asyncio.IncompleteReadError, ConnectionError):
        pass
    finally:
        writer.close()


async def run(args: argparse.Namespace, out: TextIO) -> int:
    slow_s = None if args.slow_ms is None else args.slow_ms / 1000.0
    unit = Unit(out, args.timeout_ms / 1000.0, args.stop_id, args.check_ms / 1000.0, slow_s,
                args.slow_level)
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: UdpHandler(unit), local_addr=(args.bind, args.udp_port))
    server = await asyncio.start_server(
        lambda r, w: tcp_client(unit, r, w), args.bind, args.tcp_port)
    udp_port = transport.get_extra_info("sockname")[1]
    tcp_port = server.sockets[0].getsockname()[1]
    unit.log(f"start udp={args.bind}:{udp_port} tcp={args.bind}:{tcp_port} "
             f"timeout_ms={args.timeout_ms} slow_ms={args.slow_ms or args.timeout_ms} "
             f"slow_level={args.slow_level} check_ms={args.check_ms}")
    done = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, done.set)
    task = asyncio.create_task(unit.periodic())
    failed: list[BaseException] = []

    def on_task_end(t: asyncio.Task[None]) -> None:
        # the periodic task is the watchdog and the CAN output: if it dies, end loudly
        # (a silent baseline made every bench trial wait for a stop frame that never came)
        exc = None if t.cancelled() else t.exception()
        if exc is not None:
            failed.append(exc)
            unit.log(f"periodic_task_failed error={exc!r}")
            done.set()

    task.add_done_callback(on_task_end)
    await done.wait()
    task.cancel()
    if unit.state != STOPPED:  # shutting down while armed: the host cannot go on (a fault)
        unit.state, unit.reason = STOPPED, can.Reason.FAULT
    unit.send_brake()  # the last frame requests the brake
    transport.close()
    server.close()
    unit.log("exit")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="baseline_asyncio", description=__doc__.splitlines()[0])
    ap.add_argument("--udp-port", type=int, default=5700)
    ap.add_argument("--tcp-port", type=int, default=5701)
    ap.add_argument("--bind", default="0.0.0.0")
    ap.add_argument("--timeout-ms", type=int, default=200)
    ap.add_argument("--slow-ms", type=int, default=None,
                    help="slow time S (default: the timeout, no SLOWING)")
    ap.add_argument("--slow-level", type=int, default=can.DEFAULT_SLOW_LEVEL,
                    help="brake_level while SLOWING, percent 1..99")
    ap.add_argument("--stop-id", type=lambda s: tcp.check_stop_id(int(s, 0)),
                    default=tcp.DEFAULT_STOP_ID)
    ap.add_argument("--can-log", default="-", metavar="PATH|-")
    ap.add_argument("--no-auth", action="store_true",
                    help="accepted for estopd's command line; the baseline has no key")
    ap.add_argument("--check-ms", type=float, default=10.0,
                    help="period of the watchdog check task (default 10 ms, the brake period)")
    args = ap.parse_args(argv)
    if args.slow_ms is not None and not 0 < args.slow_ms <= args.timeout_ms:
        ap.error("--slow-ms must be 1 .. --timeout-ms")
    if not can.SLOW_LEVEL_MIN <= args.slow_level <= can.SLOW_LEVEL_MAX:
        ap.error("--slow-level must be 1..99")
    if args.can_log == "-":
        return asyncio.run(run(args, sys.stdout))
    with open(args.can_log, "a", encoding="ascii") as out:
        return asyncio.run(run(args, out))


if __name__ == "__main__":
    sys.exit(main())
