"""The demo's script: the operator's tablet (the real :class:`estop.client.sender.Remote`, with
the key), its Wi-Fi link (:mod:`estop.model.wifi`) and the attacker, against a running unit
and, for the finger lift, the version-2 unit beside it (:mod:`estop.demo.twin`).

The story, version 3's: release and drive; the finger lifts (the lift datagrams stop the car at
once; the version-2 unit waits for its timeout); the attacker's forged RELEASE (NAK 4);
release and drive over a bursty link: a burst of lost packets longer than the slow time S but
shorter than the timeout T slows the car (SLOWING) and it drives on (ARMED) without a latched
stop; the tablet's Wi-Fi dies with the finger still down, while the attacker sends forged and
replayed heartbeats: SLOWING at S, STOPPED at T; release and drive; the attacker's stop
datagram stops the car (anyone may stop); release, drive, the stop button; a RELEASE with the
gas pressed (NAK 3).

Every frame the unit logs goes through :class:`estop.demo.bus.BusWatch` (and so the live car)
as it comes; the story only acts and notes the moments that matter in the
:class:`~estop.demo.result.Result`.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable

from estop.client.button import LIFT_GAP
from estop.demo.attacker import Attacker
from estop.demo.bus import Change, is_state
from estop.demo.operator import Operator
from estop.demo.result import BurstMeasure, Result, Settings, StopMeasure, settle
from estop.demo.twin import V2Twin
from estop.demo.view import View, reply_text
from estop.protocol import can
from estop.unit.canlog import DaemonError
from estop.unit.daemon import Daemon

__all__ = ["Story", "finish_run", "run_story"]

HOLD_NEUTRAL_S = 0.3  # the finger down in neutral before a RELEASE (5 packets are needed)
DRIVE_S = 1.3  # a drive: the car reaches the demo's speed within a second


def _never() -> bool:
    return False


class Story:
    """Plays the script against ``unit`` (started) with ``view`` (its watch and car); fills
    ``res``. ``twin``, when given and started, is the version-2 unit beside it."""

    def __init__(self, unit: Daemon, view: View, settings: Settings, key: bytes, res: Result,
                 twin: V2Twin | None = None) -> None:
        self.unit = unit
        self.view = view
        self.watch = view.watch
        self.car = view.car
        self.settings = settings
        self.res = res
        self.twin = twin
        self.op = Operator(unit.udp_port, unit.tcp_port, key, twin)
        self.remote = self.op.remote
        self.attacker: Attacker | None = None

    def _link_down(self) -> float:
        """Every packet lost from now on; returns when the last packet got through."""
        self.op.link_down()
        self.car.driving = False  # no packet reaches the car: no more gas
        self.wait(0.005)  # a packet the sender was handing over as the link went is in
        return self.op.last_delivered

    # --------------------------------------------------------------------------- pumping

    def pump(self, until: Callable[[], bool], max_s: float,
             side: Callable[[], None] | None = None) -> bool:
        """Take the logged frames, steer, call ``side`` every 10 ms (the attacker) and draw,
        until ``until()`` or ``max_s`` passes."""
        start = time.monotonic()
        next_side = start
        while True:
            now = time.monotonic()
            if side is not None and now >= next_side:
                side()
                next_side += 0.01
            self.op.steer(now)
            self.drain()
            self.view.remote = self.op.text()
            self.view.draw()
            if until():
                return True
            if now - start >= max_s:
                return False
            if not self.unit.alive():
                raise DaemonError("estopd exited during the demo")
            time.sleep(0.002)

    def drain(self) -> None:
        """Every frame logged so far: through the watch (and the car), changes shown."""
        while True:
            try:
                rec = self.unit.frames.get_nowait()
            except queue.Empty:
                break
            change = self.watch.take(rec)
            if change is not None:
                self.view.bus("bus", change)
        if self.twin is not None:
            for change in self.twin.drain():
                self.view.bus("v2 unit bus", change)

    def wait(self, seconds: float, side: Callable[[], None] | None = None) -> None:
        self.pump(_never, seconds, side)

    def wait_for(self, after: float, state: int, max_s: float,
                 side: Callable[[], None] | None = None) -> Change | None:
        """The first change into ``state`` at or after ``after``, waiting up to ``max_s``."""
        self.pump(lambda: self.watch.first(after, is_state(state)) is not None, max_s, side)
        return self.watch.first(after, is_state(state))

    def wait_at_rest(self) -> None:
        self.pump(lambda: self.car.at_rest, 3.0)

    # ----------------------------------------------------------------------------- story

    def run(self) -> None:
        try:
            self.boot()
            if not self.release_and_drive("the first", with_twin=True):
                return
            self.lift()
            if not self.release_and_drive("the second", before=self.forged_release):
                return
            if not self.burst():
                return
            self.loss()
            if not self.release_and_drive("the third"):
                return
            self.stop_datagram()
            if not self.release_and_drive("the fourth"):
                return
            self.stop_button()
        finally:
            self.op.close()
            if self.attacker is not None:
                self.attacker.close()
            if self.twin is not None:
                self.twin.stop()

    def boot(self) -> None:
        self.view.phase = "boot"
        self.remote.start()
        self.remote.status()
        self.view.event(time.time(), f"remote: holds the key; the unit's session "
                                     f"{self.remote.channel.session:#018x} learnt from a STATUS")
        self.wait(0.3)
        t = time.time()
        reply = self.remote.release()
        self.res.boot_release_nak = 0 if reply.ack else reply.nak_code
        self.view.event(t, f"remote: RELEASE (no packets yet) -> {reply_text(reply)}")

    def release_and_drive(self, which: str, *, with_twin: bool = False,
                          before: Callable[[], None] | None = None) -> bool:
        """The finger down in neutral, ``before()``, the operator's RELEASE, a drive; False (a
        problem noted) when the RELEASE was refused or the unit did not stay ARMED."""
        self.view.phase = "release"
        self.op.neutral()
        self.car.driving = False
        self.remote.hold()
        self.wait(HOLD_NEUTRAL_S)
        if before is not None:
            before()
        t = time.time()
        reply = self.remote.release()
        self.view.event(t, f"remote: RELEASE -> {reply_text(reply)}")
        if with_twin and self.twin is not None and self.twin.running:
            t = time.time()
            self.view.event(t, f"v2 unit: RELEASE -> {reply_text(self.twin.release())}")
        if not (reply.ack and reply.state == can.State.ARMED):
            self.res.problems.append(f"{which} RELEASE was refused")
            return False
        self.view.phase = "drive"
        self.op.drive()
        self.car.driving = True
        self.wait(DRIVE_S)
        return self._still_armed()

    def _still_armed(self) -> bool:
        b = self.watch.brake
        if b is not None and b.state == can.State.ARMED:
            return True
        reason = can.reason_name(b.reason) if b is not None else "-"
        state = can.state_name(b.state) if b is not None else "-"
        self.res.problems.append(f"the unit left ARMED during the drive ({state}, reason "
                                 f"{reason}): the demo's packets were held up longer than the "
                                 f"slow time (a very busy machine?)")
        return False

    def lift(self) -> None:
        """The finger lifts mid-drive: three lift datagrams, no more control packets."""
        self.view.phase = "finger lifts"
        self.op.hands_off()
        t = time.time()
        self.remote.lift()
        self.car.driving = False
        self.remote.wait_lift_sent()
        self.res.lift_datagrams = self.remote.lift_sent
        self.view.event(t, f"remote: the finger lifts: {self.remote.lift_sent} lift datagrams, "
                           f"{LIFT_GAP * 1000:g} ms apart, and no control packet after them")
        self.res.lift = m = StopMeasure("the finger lifts", "the lift", t)
        m.stop = self.wait_for(t, can.State.STOPPED, self.settings.timeout_ms / 1000.0 + 1.0)
        m.between = self.watch.states(t, m.stop.t if m.stop is not None else time.time())
        twin = self.twin
        if twin is not None and twin.running:
            v2 = StopMeasure(f"the same lift, v2 unit (T {twin.timeout_ms} ms)", "the lift", t,
                             unit="v2")
            self.res.v2 = v2
            self.pump(lambda: twin.watch.first(t, is_state(can.State.STOPPED)) is not None,
                      twin.timeout_ms / 1000.0 + 1.0)
            v2.stop = twin.watch.first(t, is_state(can.State.STOPPED))
        self.wait_at_rest()
        if twin is not None:
            rc = twin.stop()
            self.view.event(time.time(), f"v2 unit: ended (exit code {rc}); it got "
                                         f"{twin.forwarded} of the operator's packets")

    def _attacker(self) -> Attacker:
        if self.attacker is None:
            self.attacker = Attacker(self.unit.udp_port, self.unit.tcp_port,
                                     self.remote.channel.session, self.op.recording())
        return self.attacker

    def forged_release(self) -> None:
        self.view.phase = "forged RELEASE"
        forged = self._attacker().forged_release()
        self.res.forged_release_nak = 0 if forged.ack else forged.nak_code
        self.view.event(time.time(), f"attacker: RELEASE under a wrong key -> "
                                     f"{reply_text(forged.reply)}")

    def burst(self) -> bool:
        """A burst of lost packets, S < burst < T; False when it latched a stop."""
        s = self.settings
        self.view.phase = "bursty link"
        speed_before = self.car.speed
        t_cut = time.time()
        t_last = self._link_down()
        self.car.watch_low()
        self.view.event(t_cut, f"link: a burst begins, every packet lost for {s.burst_ms} ms "
                               f"(S {s.slow_ms} ms < burst < T {s.timeout_ms} ms); the last "
                               f"packet went through at {t_last - self.view.t0:.3f}s")
        self.pump(lambda: time.time() >= t_cut + s.burst_ms / 1000.0, s.burst_ms / 1000.0 + 1)
        t_end = time.time()
        lost = self.op.link_up()
        self.car.driving = True
        self.view.event(t_end, f"link: back after {(t_end - t_cut) * 1000:.0f} ms, "
                               f"{lost} packets lost")
        b = BurstMeasure(t_cut, t_end, t_last, lost, speed_before=speed_before)
        self.res.burst = b

        def settled() -> bool:
            slowing = self.watch.first(t_last, is_state(can.State.SLOWING))
            return (self.watch.first(t_last, is_state(can.State.STOPPED)) is not None
                    or (slowing is not None
                        and self.watch.first(slowing.t, is_state(can.State.ARMED)) is not None))

        self.pump(settled, s.timeout_ms / 1000.0 + 0.5)
        self.wait(0.8)  # driving on, back to speed
        b.first_back = self.op.first_delivered(t_end)
        b.slowing = self.watch.first(t_last, is_state(can.State.SLOWING))
        if b.slowing is not None:
            b.armed = self.watch.first(b.slowing.t, is_state(can.State.ARMED))
        b.stops = [c for c in self.watch.states(t_last, time.time() + 1.0)
                   if c.state == can.State.STOPPED]
        b.speed_low = self.car.low
        return not b.stops  # a latched stop: demo_checks says so

    def loss(self) -> None:
        """The tablet's Wi-Fi dies with the finger still down: silence and no lift."""
        s = self.settings
        self.view.phase = "Wi-Fi dies"
        t_cut = time.time()
        t_last = self._link_down()
        self.view.event(t_cut, "link: the tablet's Wi-Fi dies: the finger stays down, every "
                               "packet is lost, no lift datagram reaches the unit; the last "
                               f"packet went through at {t_last - self.view.t0:.3f}s")
        attacker = self._attacker()
        self.view.event(time.time(), "attacker: sends plain heartbeats, heartbeats under a "
                                     "wrong key and replays of the operator's recording, "
                                     "100 Hz each")
        m = StopMeasure("the Wi-Fi dies (no lift)", "the last packet", t_last)
        self.res.loss = m
        m.stop = self.wait_for(t_last, can.State.STOPPED, s.timeout_ms / 1000.0 + 2.0,
                               side=attacker.keep_alive)
        self.wait(0.1, side=attacker.keep_alive)
        self.res.attacker_sent = dict(attacker.sent)
        self.view.event(time.time(), f"attacker: sent {attacker.sent_text()} heartbeats")
        m.slowing = self.watch.first(t_last, is_state(can.State.SLOWING))
        m.between = self.watch.states(t_last, m.stop.t if m.stop is not None else time.time())
        self.wait_at_rest()
        t = time.time()
        lost = self.op.link_up()
        self.view.event(t, f"link: the Wi-Fi is back ({lost} packets were lost)")

    def stop_datagram(self) -> None:
        self.view.phase = "stop datagram"
        t = self._attacker().stop_datagram()
        self.view.event(t, "attacker: stop datagram with a garbage tag (anyone may stop)")
        m = StopMeasure("the attacker's stop datagram", "its sending", t)
        self.res.datagram = m
        m.stop = self.wait_for(t, can.State.STOPPED, 2.0)
        self.wait_at_rest()

    def stop_button(self) -> None:
        self.view.phase = "stop button"
        t = time.time()
        outcome = self.remote.press_stop()
        what = reply_text(outcome.reply) if outcome.reply is not None else outcome.summary()
        self.view.event(t, f"remote: stop button (stop datagram and STOP) -> {what}")
        m = StopMeasure("the stop button", "the press", t)
        self.res.button = m
        m.stop = self.wait_for(t, can.State.STOPPED, 2.0)
        self.wait_at_rest()
        self.view.phase = "latched"
        self.wait(0.3)  # the operator still gives gas
        t = time.time()
        reply = self.remote.release()
        self.res.latched_release_nak = 0 if reply.ack else reply.nak_code
        self.view.event(t, f"remote: RELEASE (gas still pressed) -> {reply_text(reply)}")
        self.wait(0.2)


def run_story(unit: Daemon, view: View, settings: Settings, key: bytes, res: Result,
              twin: V2Twin | None = None) -> None:
    """Play the story against ``unit`` (started); problems and measurements go to ``res``."""
    Story(unit, view, settings, key, res, twin).run()


def finish_run(unit: Daemon, view: View, res: Result,
               twin: V2Twin | None = None) -> tuple[int | None, int | None]:
    """End the daemons, take their last frames, settle the measurements; their exit codes."""
    rc = unit.stop()
    twin_rc = twin.stop() if twin is not None else None
    while True:
        try:
            rec = unit.frames.get_nowait()
        except queue.Empty:
            break
        change = view.watch.take(rec)
        if change is not None:
            view.bus("bus", change)
    view.finish()
    settle(res, unit, view.watch, twin.daemon if twin is not None else None,
           twin.watch if twin is not None else None)
    return rc, twin_rc
