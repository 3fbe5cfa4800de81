"""Bad set-ups (guest side of `make systemd-vm`): each gets one clear line in the journal and no
restart storm that hides it. Each is made, the unit restarted and watched, then put right."""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable
from pathlib import Path

import checklist
from checks_service import KEY
from guestlib import CheckFailed, Results, active_pid, journal, messages, now, sh, show, wait_for

CONF = Path("/etc/estop/estopd.conf")
WATCH_S = 3.0  # three RestartSec: a storm would start it twice more at least


@dataclasses.dataclass(frozen=True)
class BadSetup:
    name: str
    make: Callable[[], None]
    undo: Callable[[], None]
    line: str  # a regular expression the journal must hold


def set_args(extra: str) -> Callable[[], None]:
    def edit() -> None:
        text = CONF.read_text()
        CONF.with_suffix(".good").write_text(text)
        CONF.write_text(re.sub(r"^ESTOPD_ARGS=(.*)$", rf"ESTOPD_ARGS=\1 {extra}", text,
                               flags=re.M))
    return edit


def restore_conf() -> None:
    CONF.with_suffix(".good").rename(CONF)


def move_key() -> None:
    Path(KEY).rename(KEY + ".away")


def key_back() -> None:
    Path(KEY + ".away").rename(KEY)


def expose_key() -> None:
    Path(KEY).chmod(0o644)
    Path(KEY).parent.chmod(0o755)


def hide_key() -> None:
    Path(KEY).chmod(0o600)
    Path(KEY).parent.chmod(0o700)


BAD_SETUPS = [
    BadSetup(checklist.BAD_KEY_MISSING, move_key, key_back,
             r"estopd: error: --key-file '/etc/estop/key': No such file or directory"),
    BadSetup(checklist.BAD_KEY_MODE, expose_key, hide_key,
             r"estopd: error: --key-file '/etc/estop/key': group or others have access "
             r"\(mode 0644\)"),
    BadSetup(checklist.BAD_KEY_ACL,
             lambda: sh(["setfacl", "-m", "u:1000:r", KEY]) and None,
             lambda: sh(["setfacl", "-b", KEY]) and None,
             r"estopd: error: --key-file '/etc/estop/key': its ACL lets user 1000 access it"),
    BadSetup(checklist.BAD_IFACE, set_args("--channel vcan9"), restore_conf,
             r"estopd: error: no CAN interface 'vcan9'"),
    BadSetup(checklist.BAD_RT_PRIO, set_args("--rt-prio 60"), restore_conf,
             r"estopd: error: --rt-prio 60: .*CPUSchedulingPriority=60"),
]


def check(res: Results, bad: BadSetup, last: bool) -> None:
    def one() -> str:
        bad.make()
        try:
            t0 = now()
            sh(["systemctl", "restart", "estopd"], check=False, timeout=60)
            wait_for("the unit to end its start", lambda: show("ActiveState")["ActiveState"]
                     in ("inactive", "failed"), 30)
            time.sleep(WATCH_S)
            p = show("ActiveState", "Result", "NRestarts")
            msgs = messages(journal(since_mono=t0))
        finally:
            bad.undo()
        starts = [m for m in msgs if m.startswith("Starting ")]
        lines = [m for m in msgs if re.search(bad.line, m)]
        if not lines:
            raise CheckFailed(f"no line /{bad.line}/ in the journal: {msgs[-6:]}")
        if len(starts) != 1 or p["ActiveState"] == "activating":
            raise CheckFailed(f"{len(starts)} starts in {WATCH_S:.0f} s (a restart loop): {p}")
        again = ""
        if last:  # put right, the unit starts again (the next set-up restarts it anyway)
            sh(["systemctl", "start", "estopd"], timeout=60)
            active_pid(30)
            again = "; put right: running again"
        return (f"one start, then {p['ActiveState']} (result {p['Result']}), no restart in "
                f"{WATCH_S:.0f} s; journal: '{lines[0]}'{again}")
    res.run(bad.name, one)


def run(res: Results, project: Path | None = None) -> None:
    active_pid(30)
    for i, bad in enumerate(BAD_SETUPS):
        check(res, bad, last=i == len(BAD_SETUPS) - 1)
