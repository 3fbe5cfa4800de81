"""The unit follows its CAN interface (guest side of `make systemd-vm`): stopped when vcan0
goes away, started when it comes back, and at a boot without it the unit waits (no restart
loop) and starts when it appears."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import checklist
from checks_restart import STARTUP_MAX, boot_frame, first_frame_after
from checks_service import VCAN_NETDEV
from guestlib import (
    IFACE,
    BrakeFrames,
    CheckFailed,
    Results,
    active_pid,
    first_line,
    journal,
    messages,
    mono,
    now,
    sh,
    show,
    wait_for,
)

# BindsTo=: systemd stops the unit when udev reports the device gone, and the device's Wants=
# begins its start when it is back. No figure is promised (udev and a job under TCG on a busy
# machine: 0.2 to 4 s, reported); a unit that does not follow within this many seconds fails.
FOLLOW_S = 10.0
WATCH_S = 3.0  # how long a unit without its interface is watched for restarts (3 RestartSec)
BOOT_WAIT_S = 60.0  # a boot not finished by then waits for something (the device's job: 90 s)


def inactive() -> bool:
    return show("ActiveState")["ActiveState"] in ("inactive", "failed")


def starts_since(t: float) -> int:
    return sum(1 for m in messages(journal(since_mono=t)) if m.startswith("Starting "))


def check_del_add(res: Results) -> None:
    def follow() -> str:
        pid = active_pid(10)
        t0 = now()
        sh(["ip", "link", "del", IFACE])
        wait_for("estopd stopped after ip link del", inactive, 30)
        t_off = first_line(t0, r"^Stopped ")
        time.sleep(WATCH_S)
        if not inactive() or starts_since(t0) != 0:
            raise CheckFailed("started again without the interface: "
                              f"{messages(journal(since_mono=t0))}")
        frames = BrakeFrames().start()
        try:
            t1 = now()
            sh(["ip", "link", "add", IFACE, "type", "vcan"])
            new = active_pid(FOLLOW_S + STARTUP_MAX + 5, other_than=pid)
            starting = first_line(t1, r"^Starting ")
            t_on = mono(show("ActiveEnterTimestampMonotonic")["ActiveEnterTimestampMonotonic"])
            wait_for("networkd brings vcan0 up", lambda: "UP" in sh(
                ["ip", "link", "show", IFACE]).stdout.split(">")[0], 30)
            first = first_frame_after(frames, t1, "a frame after the interface came back", 10)
        finally:
            frames.close()
        if any("Scheduled restart job" in m for m in messages(journal(since_mono=t0))):
            raise CheckFailed("restarted by Restart= (BindsTo= stops and starts it)")
        if t_off - t0 > FOLLOW_S or starting - t1 > FOLLOW_S:
            raise CheckFailed(f"stopped {t_off - t0:.2f} s after del, start began "
                              f"{starting - t1:.2f} s after add (within {FOLLOW_S:.0f} s)")
        if t_on - starting > STARTUP_MAX:
            raise CheckFailed(f"the start took {t_on - starting:.2f} s")
        boot_frame(first)
        return (f"ip link del: stopped after {t_off - t0:.2f} s, no start in {WATCH_S:.0f} s; "
                f"ip link add: start began +{starting - t1:.2f} s, PID {new} READY=1 "
                f"+{t_on - t1:.2f} s, networkd set it up, first frame +{first.t - t1:.2f} s: "
                f"{first}")
    res.run(checklist.BINDSTO, follow)


def prepare_nocan(res: Results) -> None:
    """The next boot has no vcan0 (no .netdev for networkd to create it); the unit stays
    enabled as installed."""
    def prepare() -> str:
        Path(VCAN_NETDEV).unlink()
        enabled = sh(["systemctl", "is-enabled", "estopd"], check=False).stdout.strip()
        sh("sync")
        return f"{VCAN_NETDEV} removed, estopd {enabled}; powering off for the next boot"
    res.run(checklist.PREPARE_NOCAN, prepare)


def run_nocan(res: Results) -> None:
    def waits() -> str:
        if sh(["ip", "link", "show", IFACE], check=False).returncode == 0:
            raise CheckFailed(f"{IFACE} exists at this boot")
        time.sleep(WATCH_S)
        # The boot ends (running or degraded) unless a job waits: for the interface, say.
        try:
            system = sh(["systemctl", "is-system-running", "--wait"], timeout=BOOT_WAIT_S,
                        check=False).stdout.strip()
        except subprocess.TimeoutExpired:
            system = f"still starting after {BOOT_WAIT_S:.0f} s"
        booted = sh(["systemd-analyze", "time"], check=False).stdout.strip().splitlines()
        p = show("ActiveState", "SubState", "NRestarts", "MainPID")
        jobs = sh(["systemctl", "list-jobs", "--no-legend", "--no-pager"]).stdout
        targets = {t: sh(["systemctl", "is-active", t], check=False).stdout.strip()
                   for t in ("multi-user.target", "graphical.target")}
        res.fact("nocan_boot", {"unit": p, "jobs": jobs.splitlines(), "targets": targets,
                                "analyze": booted,
                                "system": system, "uptime_s": time.clock_gettime(
                                    time.CLOCK_BOOTTIME)})
        if p["ActiveState"] not in ("inactive", "activating") or int(p["MainPID"]) != 0:
            raise CheckFailed(f"estopd is running without {IFACE}: {p}")
        if int(p["NRestarts"]) != 0 or starts_since(0) != 0:
            raise CheckFailed(f"restart loop: {p}, {messages(journal())[-5:]}")
        if system not in ("running", "degraded") or any(v != "active" for v in targets.values()):
            raise CheckFailed(f"the boot waits for estopd's interface: {targets}, {system}; "
                              f"jobs: {jobs.strip()}")
        frames = BrakeFrames().start()
        try:
            t1 = now()
            sh(["ip", "link", "add", IFACE, "type", "vcan"])  # networkd's .network sets it up
            new = active_pid(FOLLOW_S + STARTUP_MAX + 5)
            starting = first_line(t1, r"^Starting ")
            t_on = mono(show("ActiveEnterTimestampMonotonic")["ActiveEnterTimestampMonotonic"])
            first = first_frame_after(frames, t1, "a frame once vcan0 is there", 10)
        finally:
            frames.close()
        if starting - t1 > FOLLOW_S or t_on - starting > STARTUP_MAX:
            raise CheckFailed(f"start began {starting - t1:.2f} s after ip link add, READY=1 "
                              f"{t_on - starting:.2f} s later")
        boot_frame(first)
        boots = ", ".join(f"{k} {v}" for k, v in targets.items())
        return (f"no {IFACE}: estopd {p['ActiveState']}/{p['SubState']}, no start, no restart "
                f"over {WATCH_S:.0f} s, system {system} ({boots}; "
                f"{booted[0] if booted else '?'}); ip link add: start began "
                f"+{starting - t1:.2f} s, PID {new} READY=1 +{t_on - t1:.2f} s, first frame "
                f"{first}")
    res.run(checklist.NOCAN,
            waits)


def run(res: Results, project: Path | None = None) -> None:
    check_del_add(res)
