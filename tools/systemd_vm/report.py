"""The host's report of `make systemd-vm`: every check of every system with what it measured,
the facts each system showed (systemd, kernel, the credential), the image and boot times, and
one closing line. A check that never reported fails (checklist.PHASES)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import checklist


def load(share: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    results = []
    path = share / "results.jsonl"
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                results.append(json.loads(line))
            except ValueError:
                continue
    facts: dict[str, Any] = {}
    for f in sorted(share.glob("facts-*.json")):
        facts.update(json.loads(f.read_text()))
    return results, facts


def prepared(share: Path) -> bool:
    """The main boot's test got through: the next boot (without vcan0) is worth booting."""
    results, _ = load(share)
    return any(r["check"] == checklist.PREPARE_NOCAN and r["ok"] for r in results)


def report(outdir: Path, names: list[str], timings: list[dict[str, object]], total_s: float,
           plant: str) -> int:
    passed = failed = 0
    for name, timing in zip(names, timings, strict=True):
        results, facts = load(outdir / name / "share")
        print(f"systemd-vm: {name}: {facts.get('systemd', '?')}, "
              f"kernel {facts.get('kernel', '?')}")
        seen = {r["check"] for r in results}
        for r in results:
            mark = "ok  " if r["ok"] else "FAIL"
            took = f" ({r['wall_s']} s, guest CPU {r['cpu_s']} s)" if "wall_s" in r else ""
            print(f"  {mark} {r['check']}{took}")
            print(f"       {r['measured'] or r['detail']}")
            passed += r["ok"]
            failed += not r["ok"]
        for phase, checks in checklist.PHASES.items():
            for check in checks:
                if check not in seen:
                    print(f"  FAIL {check}\n       never reported (phase {phase}; "
                          f"{timing.get(f'boot_{phase}_error', 'the test died')}; see "
                          f"{outdir / name})")
                    failed += 1
        cred = facts.get("credential")
        if cred:
            print(f"  credential: {cred['fstype']} ({cred['options']}), owner uid "
                  f"{cred['owner_uid']}, mode {cred['mode']}, ACL {' '.join(cred['acl'])}")
        times = ", ".join(f"{k} {v}" for k, v in timing.items() if k != "system")
        print(f"  times (s): {times}")
    print(f"systemd-vm: {total_s:.0f} s in all; output in {outdir}")
    if plant:
        print(f"systemd-vm: planted fault '{plant}': the failures above are its effect")
    print(f"systemd-vm: {passed} passed, {failed} failed")
    return 1 if failed else 0
