"""The keyed rows (spec section 5): forged and genuine RELEASE, the dead-man under spoofed
heartbeats, a stop datagram with a garbage tag, a replay after a restart.
"""

from __future__ import annotations

import os
import socket
import threading
import time

from estop.protocol import auth, udp
from estop.protocol.can import BRAKE_ID
from hilclients import NEUTRAL, AuthClient, AuthRemote, UdpRemote, wrong_key
from hiljudge import (
    judge,
    judge_spoiled,
    last_packet,
    link_died_first,
    no_armed_frame,
    show_ex,
    windows_in,
)
from hilload import udp_drops
from hilrun import EARLY_TOL_MS, TIMEOUT_MS, Result, Row, Run

# The attacker's send period.
ATTACK_PERIOD_S = 0.005


# ------------------------------------------------------------------ keyed rows (spec section 5)
# These run last, on a daemon started with --key-file (a key made for the run, mode 0600, in
# the output directory). The key holder's remote (hilclients.AuthRemote) learns the session with a
# STATUS request frame and verifies every reply's tag under the key.

def attack_packets(ar: AuthRemote, key: bytes, replay: list[bytes]) -> list[tuple[str, bytes]]:
    """What an attacker without the key sends to keep the unit alive, one of each kind in turn:
    a plain heartbeat, one under a wrong key (the right session and remote id, which travel in
    clear, and counters above the remote's), and the remote's own recorded heartbeats again."""
    body = udp.decode(NEUTRAL)
    forged = [auth.AuthControlPacket(ar.remote_id, ar.session, ar.udp_counter + 1000 + i,
                                     body).encode(wrong_key(key)) for i in range(len(replay))]
    out: list[tuple[str, bytes]] = []
    for i, rec in enumerate(replay):
        out += [("plain", NEUTRAL), ("wrong_key", forged[i]), ("replay", rec)]
    return out


class Attacker:
    """A thread that sends ``packets`` in turn, one every ATTACK_PERIOD_S, until stopped."""

    def __init__(self, remote: UdpRemote, packets: list[tuple[str, bytes]]) -> None:
        self.remote = remote
        self.packets = packets
        self.sent: dict[str, int] = {}
        self.t0 = self.t1 = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="attacker", daemon=True)

    def _run(self) -> None:
        i = 0
        self.t0 = time.time()
        nxt = time.monotonic()
        while not self._stop.is_set():
            kind, data = self.packets[i % len(self.packets)]
            errors = self.remote.errors
            self.remote.send(data)
            if self.remote.errors == errors:  # not refused (an ICMP error from earlier)
                self.sent[kind] = self.sent.get(kind, 0) + 1
            i += 1
            nxt += ATTACK_PERIOD_S
            self._stop.wait(max(0.0, nxt - time.monotonic()))
        self.t1 = time.time()

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


def count_check(run: Run, res: Result, t0: float, t1: float, invalid: int, auth_failed: int,
                drops: int | None) -> None:
    """ESTOP_STATUS over ``[t0, t1]`` counted exactly ``invalid`` invalid packets, of which
    ``auth_failed`` failed authentication (bytes 1 and 2); the kernel dropped ``drops``."""
    ws = windows_in(run, t0, t1)
    got_inv = sum(w.invalid for w in ws)
    got_auth = sum(w.auth_failures for w in ws)
    res.figures["status_counted"] = {"invalid": got_inv, "auth_failures": got_auth,
                                     "windows": len(ws), "kernel_drops": drops}
    if drops:
        res.inconclusive = f"the kernel dropped {drops} packets at the daemon's socket"
        res.check(False, f"ESTOP_STATUS counts not judged: {drops} packets dropped")
        return
    res.check(drops is not None, "no daemon socket in /proc/net/udp")
    res.check(got_inv == invalid, f"ESTOP_STATUS byte 1 counted {got_inv} invalid packets, "
                                  f"{invalid} were sent")
    res.check(got_auth == auth_failed, f"ESTOP_STATUS byte 2 counted {got_auth} authentication "
                                       f"failures, {auth_failed} were sent")


def sc_auth_release(run: Run, res: Result) -> None:
    ar = run.auth_remote()
    key = run.ensure_key()
    res.figures["session"] = f"{ar.session:#018x}"
    start = run.mon.index()
    t0 = time.time()
    ar.start(NEUTRAL)  # a live authenticated neutral link: only the key can be missing
    run.wait_packets(ar, t0)
    # A forger who read the session and the remote id off the air, with counters above the
    # remote's, and the wrong key.
    forger = AuthClient(run.tcp_port, wrong_key(key), key, ar.remote_id)
    forger.session, forger.counter = ar.session, ar.tcp.counter + 1000
    try:
        exf = forger.release()
    finally:
        forger.close()
    res.figures["forged_release"] = show_ex(exf)
    res.check(not exf.reply.ack and exf.reply.nak_code == 4,
              "RELEASE under a wrong key: not NAK 4")
    res.check(exf.tag_ok is True, "the unit's reply to the forged RELEASE does not verify")
    exp = run.clients[1].release()
    res.figures["plain_release"] = show_ex(exp)
    res.check(not exp.reply.ack and exp.reply.nak_code == 4,
              "plain RELEASE on a unit with a key: not NAK 4")
    time.sleep(0.05)
    no_armed_frame(run, res, start, "an ARMED frame after a forged or plain RELEASE")
    start2 = run.mon.index()
    ex = ar.release()
    res.figures["genuine_release"] = show_ex(ex)
    res.check(ex.tag_ok is True, "the reply to the genuine RELEASE does not verify")
    res.check(ex.reply.ack and ex.reply.state == 1,
              "genuine RELEASE with a live authenticated link: not ACK ARMED")
    got = run.brake_after(start2, lambda b: b.state == 1, 1.0, after=ex.t_send)
    if got is None:
        res.check(False, "no ARMED frame after the genuine RELEASE")
    else:
        judge(run, res, "release_to_armed_frame_ms", "authenticated release -> ARMED frame",
              [(ex.t_send, got[0].ts)], use_median=False)
    time.sleep(0.25)  # the ESTOP_STATUS frame after the forged RELEASE
    run.keepalive_held(res, t0, time.time())
    # Byte 2 counts the forged RELEASE and the plain one (it needs authentication and has no
    # tag: docs/PROTOCOL.md 5, issue 16).
    ws = windows_in(run, t0, time.time() - 0.1)
    res.figures["status_auth_failures"] = sum(w.auth_failures for w in ws)
    res.check(sum(w.auth_failures for w in ws) == 2,
              "ESTOP_STATUS byte 2 did not count the forged and the plain RELEASE")
    ar.stop()
    time.sleep(0.3)


def sc_auth_spoof(run: Run, res: Result) -> None:
    ar = run.auth_remote()
    key = run.ensure_key()
    over: list[tuple[float, float]] = []
    sent: dict[str, int] = {}
    t_first: float | None = None
    drops0 = udp_drops(run.udp_port)
    spoiled = 0
    for i in range(run.args.repeat):
        run.arm(res, remote=ar)
        time.sleep(0.1)
        replay = [p for _, p in ar.recorded[-10:]]  # the remote's latest heartbeats
        start = run.mon.index()
        # The last genuine packet just after a periodic frame (as in the dead-man row).
        t_last = last_packet(run, res, ar, i)
        if t_last is None:
            spoiled += 1
            time.sleep(0.3)
            continue
        attacker = Attacker(run.udp, attack_packets(ar, key, replay))
        attacker.start()  # the finger is off: only the attacker sends now
        got = run.brake_after(start, lambda b: b.state == 0, 1.0, after=t_last)
        time.sleep(0.03)
        attacker.stop()
        t_first = attacker.t0 if t_first is None else t_first
        for k, v in attacker.sent.items():
            sent[k] = sent.get(k, 0) + v
        if got is None:
            res.check(False, f"run {i}: still ARMED 1 s after the last genuine packet")
            continue
        fr, b = got
        res.check(b.reason == 3, f"run {i}: stop reason {b.reason}, want 3 udp timeout")
        over.append((t_last + TIMEOUT_MS / 1000, fr.ts))
    judge(run, res, "overshoot_ms", "dead-man overshoot under spoofing", over)
    res.figures["attack_sent"] = dict(sent)
    time.sleep(0.25)
    drops1 = udp_drops(run.udp_port)
    if t_first is not None:
        drops = drops1[1] - drops0[1] if drops0 and drops1 else None
        # Every kind fails authentication: the plain heartbeat too (no tag; issue 16).
        count_check(run, res, t_first, time.time() - 0.1, sum(sent.values()),
                    sent.get("plain", 0) + sent.get("wrong_key", 0) + sent.get("replay", 0),
                    drops)
    judge_spoiled(res, spoiled, run.args.repeat, len(over), "not every run stopped",
                  keepalive=False)


def sc_auth_stop_datagram(run: Run, res: Result) -> None:
    ar = run.auth_remote()
    lat: list[tuple[float, float]] = []
    spoiled = 0
    n = run.args.repeat
    for i in range(n):
        t_arm = time.time()
        run.arm(res, remote=ar)
        time.sleep(0.05)
        # A stop datagram from someone without the key: random session, remote id and tag.
        dg = auth.stop_datagram(i + 1, i + 1, session=int.from_bytes(os.urandom(8), "little"),
                                remote_id=int.from_bytes(os.urandom(4), "little"))
        dg = dg[:32] + os.urandom(16)
        start = run.mon.index()
        t_send = run.udp.send(dg)
        got = run.brake_after(start, lambda b: b.state == 0, 1.0, after=t_send)
        ar.stop()
        if got is not None and link_died_first(ar, t_arm, t_send, got[1].reason):
            spoiled += 1  # the harness let the link die before its datagram: not a sample
            continue
        if got is None:
            res.check(False, f"run {i}: no STOPPED frame within 1 s of the stop datagram")
            continue
        fr, b = got
        res.check(b.reason == 2, f"run {i}: bus reason {b.reason}, want 2 (stop request)")
        lat.append((t_send, fr.ts))
        time.sleep(0.02)
    judge(run, res, "stop_frame_latency_ms", "stop datagram -> stop frame", lat)
    ex = run.clients[2].status()
    res.figures["status_after"] = show_ex(ex)
    res.check(ex.reply.state == 0 and ex.reply.reason == 2, "STATUS is not STOPPED reason 2")
    try:
        data = run.udp.sock.recv(128, socket.MSG_DONTWAIT)
        res.check(False, f"a datagram came back over UDP: {data[:16].hex(' ')}")
    except BlockingIOError:
        pass
    except OSError as exc:
        res.figures["udp_socket_error"] = str(exc)
    judge_spoiled(res, spoiled, n, len(lat), "not every stop datagram showed on the bus",
                  keepalive=True)
    time.sleep(0.25)


def sc_auth_replay(run: Run, res: Result) -> None:
    ar = run.auth_remote()
    key = run.ensure_key()
    run.arm(res, remote=ar)  # recorded: these heartbeats and this RELEASE
    release = ar.tcp.sent[-1]
    time.sleep(0.1)
    ar.stop()
    recording = [p for _, p in ar.recorded[-15:]]
    old = ar.session
    time.sleep(0.3)
    # A new session: the unit restarts; an attacker replays the recording at its own pace.
    d, first = run.restart_daemon("replay after a restart")
    drops0 = udp_drops(run.udp_port)
    start = run.mon.index()
    t0 = time.time()
    replayed = 0
    for p in recording:
        errors = run.udp.errors
        run.udp.send(p)
        replayed += run.udp.errors == errors  # not refused (an ICMP error from earlier)
        time.sleep(0.02)
    replayer = AuthClient(run.tcp_port, None, key, ar.remote_id)
    try:
        ex = replayer.exchange(release)
    finally:
        replayer.close()
    res.figures["replayed_release"] = show_ex(ex)
    res.check(not ex.reply.ack and ex.reply.nak_code == 4,
              "recorded RELEASE replayed after a restart: not NAK 4")
    res.check(ex.tag_ok is True, "the unit's reply to the replayed RELEASE does not verify")
    new = ex.auth.session if ex.auth is not None else 0
    res.figures["sessions"] = f"{old:#018x} -> {new:#018x}"
    res.check(new not in (0, old), "the restarted unit kept its session (or has none)")
    time.sleep(0.25)
    drops1 = udp_drops(run.udp_port)
    run.mon.sync()
    armed = [f for f in run.mon.since(start) if f.can_id == BRAKE_ID and f.data[2] != 0]
    res.check(not armed, "left STOPPED after the replay")
    st = run.clients[0].status()
    res.figures["status_after"] = show_ex(st)
    res.check(st.reply.state == 0 and st.reply.reason == 1, "STATUS is not STOPPED boot")
    # Every replayed heartbeat is invalid (old session) and an authentication failure; so is
    # the replayed RELEASE (byte 2 only).
    drops = drops1[1] - drops0[1] if drops0 and drops1 else None
    count_check(run, res, t0, time.time() - 0.1, replayed, replayed + 1, drops)
    lrn = ar.learn_session()
    res.check(lrn.tag_ok is True and ar.session == new,
              "the remote did not learn the new session from a STATUS")
    res.check(d.alive, "daemon exited")


ROWS: list[Row] = [
    ("auth_release", "Keyed: forged and genuine RELEASE",
     "with a live authenticated link: RELEASE under a wrong key NAK 4, plain RELEASE NAK 4, no "
     "ARMED frame, byte 2 counts 2; genuine RELEASE ACK ARMED, ARMED frame <= {max} ms; reply "
     "tags verify", sc_auth_release),
    ("auth_spoof", "Keyed: dead-man under spoofed heartbeats",
     "plain, wrong-key and replayed heartbeats after the last genuine one: reason udp_timeout; "
     f"overshoot >= -{EARLY_TOL_MS}, " "p50 <= {p50}, max <= {max} ms; ESTOP_STATUS byte 1 "
     "counts all, byte 2 all of them too", sc_auth_spoof),
    ("auth_stop_datagram", "Stop datagram with a garbage tag",
     "ARMED -> STOPPED reason 2: p50 <= {p50}, max <= {max} ms; no UDP reply",
     sc_auth_stop_datagram),
    ("auth_replay", "Keyed: replay after a restart",
     "recorded heartbeats and RELEASE replayed to the restarted unit: RELEASE NAK 4, stays "
     "STOPPED/boot, new session; byte 1 counts the heartbeats, byte 2 them and the RELEASE",
     sc_auth_replay),
]
# Rows that need the daemon with a key (they run last; the others run keyless).
KEYED = {"auth_release", "auth_spoof", "auth_stop_datagram", "auth_replay"}
