"""The test inside the VM (guest side of `make systemd-vm`, issue 26), started at boot by
estop-vmtest.service: the project is installed as docs/DEPLOY.md says, then checked as a team on
a car would. Results go to results.jsonl in the output share (guestlib.Results).

The kernel command line says what to do:
  estop_vm.phase=main   install, then every check with the interface present; before powering
                        off, leaves the unit enabled with no vcan0 for the next boot
  estop_vm.phase=nocan  the boot without vcan0: the unit waits, then follows the interface
  estop_vm.plant=NAME   a fault planted after the install (plants.py), to show a check fail
  estop_vm.script=FILE  run FILE from the output share instead (a developer's probe)
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import traceback
from pathlib import Path

import checks_bad
import checks_bind
import checks_restart
import checks_service
import plants
from guestlib import Results, sh


def cmdline() -> dict[str, str]:
    words = Path("/proc/cmdline").read_text().split()
    return dict(w[len("estop_vm."):].split("=", 1) for w in words
                if w.startswith("estop_vm.") and "=" in w)


def system_name() -> str:
    osr = Path("/etc/os-release").read_text()
    m = re.search(r'^VERSION_ID="?(\d+)', osr, re.M)
    return f"debian{m[1]}" if m else "unknown"


def facts(res: Results) -> None:
    res.fact("systemd", sh(["systemctl", "--version"]).stdout.splitlines()[0])
    res.fact("kernel", os.uname().release)
    res.fact("python", sys.version.split()[0])
    res.fact("uptime_at_test_s", float(Path("/proc/uptime").read_text().split()[0]))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--project", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    opts = cmdline()
    phase = opts.get("phase", "main")
    res = Results(args.out, system_name(), phase)
    facts(res)
    if "script" in opts:  # a developer's probe: its output, nothing checked
        sh(f"sh -x {args.out / opts['script']} > {args.out / 'script.out'} 2>&1", timeout=900,
           check=False)
        return 0
    try:
        if phase == "main":
            ok = checks_service.install(res, args.project)
            if ok:
                plants.plant(opts.get("plant", ""), res)
                checks_service.run(res, args.project)
                checks_restart.run(res, args.project)
                checks_bind.run(res)
                checks_bad.run(res)
                checks_service.run_last(res, args.project)
                checks_bind.prepare_nocan(res)
        elif phase == "nocan":
            checks_bind.run_nocan(res)
    except Exception:
        res.record("the test itself", False, "", traceback.format_exc()[-1500:])
    finally:
        sh(f"journalctl -b -o short-monotonic --no-pager > {args.out}/journal-{phase}.txt",
           check=False, timeout=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())
