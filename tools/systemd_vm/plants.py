"""Faults planted after the install (`tools/systemd-vm --plant NAME`) to show that the checks
can fail: each names the checks it must break. The unit is changed as a team could change it
(a drop-in, or the installed file edited), then reloaded and restarted."""

from __future__ import annotations

from pathlib import Path

from guestlib import Results, sh

UNIT_FILE = Path("/usr/local/lib/systemd/system/estopd.service")
DROPIN = Path("/etc/systemd/system/estopd.service.d/plant.conf")


def dropin(text: str) -> None:
    DROPIN.parent.mkdir(parents=True, exist_ok=True)
    DROPIN.write_text("[Service]\n" + text + "\n")


def drop_lines(prefix: str) -> None:
    lines = UNIT_FILE.read_text().splitlines()
    UNIT_FILE.write_text("\n".join(line for line in lines if not line.startswith(prefix)) + "\n")


# name: (what it does, the checks it must break, how)
PLANTS = {
    "type-simple": ("a unit without Type=notify (Type=simple)", "systemctl start",
                    lambda: dropin("Type=simple")),
    "key-mode": ("a key the daemon refuses (chmod 0644 /etc/estop/key)", "systemctl start",
                 lambda: Path("/etc/estop/key").chmod(0o644)),
    "watchdog-never-pinged": ("a watchdog that is never pinged (WATCHDOG_PID names another "
                              "process, so estopd does not ping)", "runs steadily",
                              lambda: dropin("Environment=WATCHDOG_PID=1")),
    "no-watchdog": ("no watchdog (WatchdogSec=0)", "kill -STOP",
                    lambda: dropin("WatchdogSec=0")),
    "restart-no": ("Restart=no", "kill -9", lambda: dropin("Restart=no")),
    "restart-slow": ("RestartSec=5s", "kill -9", lambda: dropin("RestartSec=5s")),
    "no-bindsto": ("the unit without BindsTo=", "BindsTo",
                   lambda: drop_lines("BindsTo=")),
    "no-exec-condition": ("the unit without its ExecCondition= checks", "bad set-up",
                          lambda: drop_lines("ExecCondition=")),
    "no-fifo": ("no real-time scheduling (CPUSchedulingPolicy=other)", "the process",
                lambda: dropin("CPUSchedulingPolicy=other")),
    "no-sandbox": ("capabilities kept (CapabilityBoundingSet=~, AmbientCapabilities=CAP_NET_ADMIN)",
                   "the process, systemd-analyze security",
                   lambda: dropin("CapabilityBoundingSet=CAP_NET_ADMIN CAP_SYS_NICE\n"
                                  "AmbientCapabilities=CAP_NET_ADMIN")),
    "no-sysctl": ("the sysctl file not applied (net.core.rmem_max back to 212992)",
                  "systemctl start (udp_rcvbuf)",
                  lambda: sh(["sysctl", "-w", "net.core.rmem_max=212992"]) and None),
}


def plant(name: str, res: Results) -> None:
    if not name:
        return
    what, breaks, how = PLANTS[name]
    how()
    sh(["systemctl", "daemon-reload"], timeout=120)
    sh(["systemctl", "restart", "estopd"], check=False, timeout=120)
    res.fact("plant", f"{name}: {what} (must break: {breaks})")
