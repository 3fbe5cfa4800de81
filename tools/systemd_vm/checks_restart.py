"""Whatever ends the daemon, systemd starts it again (guest side of `make systemd-vm`): kill -9,
a stopped loop caught by the watchdog, and `systemctl stop` (whose last frame must brake)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import checklist
from checks_service import arm
from guestlib import (
    BrakeFrames,
    CheckFailed,
    Frame,
    Results,
    active_pid,
    first_line,
    journal,
    messages,
    mono,
    now,
    sh,
    show,
    timing_failed,
    wait_for,
)

RESTART_SEC = 1.0
WATCHDOG_SEC = 1.0
# systemd's slack on its timers under TCG: a restart is scheduled within RestartSec + this of
# the death, the watchdog fires within WatchdogSec + this of the last ping. 0.5 s until a
# fresh-machine run of 8e6ae75 (issue 24), where Debian 13's guest beside make prove scheduled
# the watchdog's restart 3.09 s after SIGSTOP, against 3.00 s allowed, with no freeze its
# kernel saw. A restart that is too slow by a unit's setting still fails (the restart-slow
# plant: RestartSec=5s against kill -9's 2 s), and one too early always does.
TIMER_SLACK = 1.0
# A start (the ExecCondition= checks, the exec, READY=1) that takes longer hangs: seconds. (No
# figure is promised for it: under TCG on a busy machine it took 0.4 to 6 s; the report says.)
STARTUP_MAX = 10.0
STEADY_S = 2.0  # two watchdog periods: a daemon that never pings is killed after one


def restart_times(t0: float, pid: int, death: float) -> tuple[float, float, float]:
    """After the daemon pid was made to die (at t0 + death at the earliest): when systemd
    scheduled the restart, began the start, and got READY=1 from the new daemon; CheckFailed
    where the restart came early or late, or the start took too long. Journal stamps are taken
    when a line arrives, never before its event: a lower bound holds on them, an upper bound
    has TIMER_SLACK."""
    scheduled = first_line(t0, r"Scheduled restart job")
    starting = first_line(scheduled, r"^Starting ")
    ready = mono(show("ActiveEnterTimestampMonotonic")["ActiveEnterTimestampMonotonic"])
    low = death + RESTART_SEC
    high = (WATCHDOG_SEC + TIMER_SLACK if death else 0.0) + RESTART_SEC + TIMER_SLACK
    if not low <= scheduled - t0 <= high:
        raise timing_failed(t0, f"restart of PID {pid} scheduled {scheduled - t0:.2f} s after "
                                f"it was made to die (RestartSec=1s: {low:.2f}..{high:.2f} s)")
    if ready - starting > STARTUP_MAX:
        raise timing_failed(t0, f"the start took {ready - starting:.2f} s (over "
                                f"{STARTUP_MAX:.0f} s)")
    return scheduled, starting, ready


def first_frame_after(frames: BrakeFrames, t: float, what: str, timeout: float) -> Frame:
    return wait_for(what, lambda: frames.first_since(t), timeout)  # type: ignore[no-any-return]


def boot_frame(f: Frame) -> None:
    if not (f.brakes and f.state == "STOPPED" and f.reason == "boot" and f.counter == 0):
        raise CheckFailed(f"first frame after the restart is {f}, not the boot frame "
                          f"(01 64 00 01 .., counter 0)")


def check_steady(res: Results) -> None:
    def steady() -> str:
        pid = active_pid(10)
        before = int(show("NRestarts")["NRestarts"])
        time.sleep(STEADY_S)
        p = show("MainPID", "NRestarts", "ActiveState")
        if int(p["MainPID"]) != pid or int(p["NRestarts"]) != before:
            raise CheckFailed(f"restarted within {STEADY_S:.0f} s: {p}, before pid {pid}, "
                              f"{before} restarts; {messages(journal())[-3:]}")
        return f"same PID {pid}, no restart over {STEADY_S:.0f} s (WatchdogSec=1s: it pings)"
    res.run(checklist.STEADY, steady)


def check_kill9(res: Results) -> None:
    def kill9() -> str:
        frames = BrakeFrames().start()
        try:
            pid = active_pid(10)
            n0 = int(show("NRestarts")["NRestarts"])
            time.sleep(0.3)
            t0 = now()
            os.kill(pid, signal.SIGKILL)
            new = active_pid(RESTART_SEC + TIMER_SLACK + STARTUP_MAX + 5, other_than=pid)
            first = first_frame_after(frames, t0 + 0.02, "a frame of the new daemon", 5)
        finally:
            frames.close()
        died = first_line(t0, r"Main process exited")
        scheduled, starting, ready = restart_times(t0, pid, 0.0)
        n1 = int(show("NRestarts")["NRestarts"])
        if n1 != n0 + 1:
            raise CheckFailed(f"NRestarts {n0} -> {n1}")
        boot_frame(first)
        return (f"PID {pid} -> {new}: died +{died - t0:.2f} s, restart scheduled "
                f"+{scheduled - t0:.2f} s, start +{starting - t0:.2f} s, READY=1 "
                f"+{ready - t0:.2f} s (start-up {ready - starting:.2f} s), first frame "
                f"+{first.t - t0:.2f} s: {first}")
    res.run(checklist.KILL9, kill9)


def check_watchdog(res: Results) -> None:
    def sigstop() -> str:
        frames = BrakeFrames().start()
        try:
            pid = active_pid(10)
            time.sleep(0.3)
            t0 = now()
            os.kill(pid, signal.SIGSTOP)
            new = active_pid(WATCHDOG_SEC + RESTART_SEC + 2 * TIMER_SLACK + STARTUP_MAX + 5,
                             other_than=pid)
            first = first_frame_after(frames, t0 + 0.02, "a frame of the new daemon", 5)
            before = [f for f in frames.since(t0 - 0.5) if f.t < t0 + 0.02]
        finally:
            frames.close()
        fired = first_line(t0, r"Watchdog timeout")
        died = first_line(fired, r"Main process exited")
        # It pings four times per WatchdogSec: the watchdog fires 0.75 s after the stop at the
        # earliest, and may take TIMER_SLACK more.
        scheduled, starting, ready = restart_times(t0, pid, 0.75 * WATCHDOG_SEC)
        if fired - t0 > WATCHDOG_SEC + TIMER_SLACK:
            raise timing_failed(t0, f"watchdog fired {fired - t0:.2f} s after SIGSTOP "
                                    f"(WatchdogSec=1s)")
        if died - fired > 2 * TIMER_SLACK:
            raise timing_failed(t0, f"the stopped daemon died {died - fired:.2f} s after the "
                                    f"watchdog fired (SIGABRT, then SIGKILL only after "
                                    f"TimeoutAbortSec?)")
        if not any("result 'watchdog'" in m for m in messages(journal(since_mono=t0))):
            raise CheckFailed("not ended with result 'watchdog'")
        boot_frame(first)
        last_old = before[-1].t - t0 if before else float("nan")
        return (f"PID {pid} stopped: watchdog fired +{fired - t0:.2f} s, died "
                f"+{died - t0:.2f} s, restart scheduled +{scheduled - t0:.2f} s, PID {new} "
                f"READY=1 +{ready - t0:.2f} s (start-up {ready - starting:.2f} s); frames silent "
                f"from {last_old:+.2f} s to +{first.t - t0:.2f} s, then {first}")
    res.run(checklist.WATCHDOG, sigstop)


def check_stop(res: Results, project: Path) -> None:
    def stop() -> str:
        frames = BrakeFrames().start()
        try:
            remote, _armed = arm(project, frames)
            t1 = now()
            sh(["systemctl", "stop", "estopd"], timeout=30)
            t2 = now()
            time.sleep(0.3)
            remote.kill()
            remote.wait(timeout=10)
            sent = frames.since(t1)
            state = show("ActiveState", "Result")
        finally:
            frames.close()
            sh(["systemctl", "start", "estopd"], timeout=60, check=False)
        if not sent:
            raise CheckFailed("no frame between systemctl stop and the end")
        last = sent[-1]
        if not last.brakes:
            raise CheckFailed(f"the last frame does not brake: {last}")
        if last.t > t2 + 0.05:
            raise CheckFailed(f"a frame {last.t - t2:.2f} s after systemctl stop returned")
        active_pid(STARTUP_MAX + 5)
        return (f"stopped while ARMED in {t2 - t1:.2f} s ({state['ActiveState']}, result "
                f"{state['Result']}); last frame {last} at {last.t - t1:.2f} s; started again")
    res.run(checklist.STOP, stop)


def run(res: Results, project: Path) -> None:
    check_steady(res)
    check_kill9(res)
    check_watchdog(res)
    check_stop(res, project)
