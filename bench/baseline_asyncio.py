"""The baseline: the estop rules as a team would write them without estopd.

A straightforward Python asyncio daemon with the same options and outputs as estopd (section 5
of PROTOCOL.md), so ``bench/stop_latency.py`` measures both identically:

- boots STOPPED (reason boot); STOPPED is latched; RELEASE needs a live link (a valid packet
  less than the timeout ago and >= 5 valid packets since the stop) and a neutral last packet;
- a UDP ``DatagramProtocol`` validates control packets and records the time of the latest one;
- the TCP stop channel is an ``asyncio.start_server`` handler reading 16-byte frames;
- one periodic task (``asyncio.sleep`` of the check period, 10 ms = the brake period) checks
  the watchdog and sends ESTOP_BRAKE every 10 ms and ESTOP_STATUS every 100 ms; state changes
  send a brake frame at once.

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

from estop.protocol import can, canlog, tcp, udp

STOPPED, ARMED = can.State.STOPPED, can.State.ARMED
R_NONE, R_BOOT = can.Reason.NONE, can.Reason.BOOT
R_TCP_STOP, R_UDP_TIMEOUT = can.Reason.TCP_STOP, can.Reason.UDP_TIMEOUT
RELEASE_PACKETS = 5


def _sat(v: int, top: int = 255) -> int:
    return v if v < top else top


class Unit:
    """The watchdog state, the CAN output, and the periodic task."""

    def __init__(self, out: TextIO, timeout_s: float, stop_id: int, check_s: float) -> None:
        self.out = out
        self.timeout_s = timeout_s
        self.warn_s = timeout_s / 2.0
        self.stop_id = stop_id
        self.check_s = check_s
        self.state: int = STOPPED
        self.reason: int = R_BOOT
        self.last_valid = 0.0  # monotonic time of the latest valid packet (0: none)
        self.last_neutral = False
        self.valid_run = 0
        self.brake_counter = 0
        self.status_counter = 0
        self.n_valid = self.n_invalid = self.n_bad_crc = self.n_stops = 0
        self.next_brake = 0.0
        self.next_status = 0.0

    # -- output --------------------------------------------------------------------------
    def log(self, text: str) -> None:
        sys.stderr.write(f"baseline {time.monotonic():.6f} {text}\n")
        sys.stderr.flush()

    def _emit(self, can_id: int, data: bytes) -> None:
        canlog.write_record(self.out, canlog.CanLogRecord.at(time.time(), "estop", can_id, data))

    def flags(self) -> int:
        if self.state == ARMED and time.monotonic() - self.last_valid >= self.warn_s:
            return 1
        return 0

    def send_brake(self) -> None:
        frame = can.BrakeFrame.for_state(self.state, self.reason, self.flags(),
                                         self.brake_counter)
        self._emit(can.BRAKE_ID, frame.encode())
        self.brake_counter = (self.brake_counter + 1) % 15
        self.next_brake = time.monotonic() + 0.010

    def send_status(self) -> None:
        age = time.monotonic() - self.last_valid
        age_ms = int(age * 1000) if self.last_valid and age < self.timeout_s else 0xFFFF
        # counts per window (since the last STATUS); stops is a nibble since version 3
        frame = can.StatusFrame(_sat(self.n_valid), _sat(self.n_invalid), 0,  # no key: no auth
                                _sat(self.n_stops, can.NIBBLE_MAX), age_ms, self.status_counter)
        self._emit(can.STATUS_ID, frame.encode())
        self.n_valid = self.n_invalid = self.n_stops = 0
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
        if self.state == ARMED:
            self.n_stops += 1
            self.set_state(STOPPED, reason, src)

    def link_live(self) -> bool:
        return (self.last_valid > 0 and time.monotonic() - self.last_valid < self.timeout_s
                and self.valid_run >= RELEASE_PACKETS)

    def on_udp(self, data: bytes) -> None:
        try:
            pkt = udp.ControlPacket.decode(data)
        except udp.InvalidPacket:
            self.n_invalid += 1
            return
        self.n_valid += 1
        self.last_valid = time.monotonic()
        self.last_neutral = pkt.is_neutral
        self.valid_run += 1

    def on_request(self, req: tcp.Request, src: str) -> bytes:
        kind = req.kind(self.stop_id)
        nak = 0
        if kind == "stop":
            self.stop(R_TCP_STOP, src)
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
            if self.state == ARMED and now - self.last_valid >= self.timeout_s:
                self.stop(R_UDP_TIMEOUT, "-")
            if now >= self.next_brake:
                self.send_brake()
            if now >= self.next_status:
                self.send_status()


class UdpHandler(asyncio.DatagramProtocol):
    def __init__(self, unit: Unit) -> None:
        self.unit = unit

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.unit.on_udp(data)


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
    unit = Unit(out, args.timeout_ms / 1000.0, args.stop_id, args.check_ms / 1000.0)
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: UdpHandler(unit), local_addr=(args.bind, args.udp_port))
    server = await asyncio.start_server(
        lambda r, w: tcp_client(unit, r, w), args.bind, args.tcp_port)
    udp_port = transport.get_extra_info("sockname")[1]
    tcp_port = server.sockets[0].getsockname()[1]
    unit.log(f"start udp={args.bind}:{udp_port} tcp={args.bind}:{tcp_port} "
             f"timeout_ms={args.timeout_ms} check_ms={args.check_ms}")
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
    if unit.state == ARMED:  # shutting down while armed: the host cannot go on (a fault)
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
    ap.add_argument("--stop-id", type=lambda s: tcp.check_stop_id(int(s, 0)),
                    default=tcp.DEFAULT_STOP_ID)
    ap.add_argument("--can-log", default="-", metavar="PATH|-")
    ap.add_argument("--no-auth", action="store_true",
                    help="accepted for estopd's command line; the baseline has no key")
    ap.add_argument("--check-ms", type=float, default=10.0,
                    help="period of the watchdog check task (default 10 ms, the brake period)")
    args = ap.parse_args(argv)
    if args.can_log == "-":
        return asyncio.run(run(args, sys.stdout))
    with open(args.can_log, "a", encoding="ascii") as out:
        return asyncio.run(run(args, out))


if __name__ == "__main__":
    sys.exit(main())
