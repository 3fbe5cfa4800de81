"""The dashboard's cost: ``estop dashboard`` following a can-log written at 100 ESTOP_BRAKE
frames a second plus 10 ESTOP_STATUS (the unit's own rates), with the page open in Debian's
chromium (headless, Playwright through the system executable).

Goals (issue 18): the server uses under 5 % of one core, and the browser receives at most 20
updates a second. Figures: the server's CPU time over the run (utime + stime from /proc),
the updates the page counted in each second, and beside them a peer on the same stream:
``estop monitor --log -`` reading it through ``tail -f`` (the same decoding, no web side).

Output: printed, and bench/out/dashboard_load.json. Usage: bench/dashboard_load.py
[--seconds 20]. Not part of `make test` (figures, not a timed test).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from estop.protocol.can import BrakeFrame, Reason, State, StatusFrame
from estop.protocol.canlog import CanLogRecord, format_line

OUT = Path(__file__).resolve().parent / "out"
TICK = os.sysconf("SC_CLK_TCK")
BRAKE_HZ, STATUS_HZ = 100, 10
GOAL_CPU, GOAL_UPDATES = 5.0, 20


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process, in seconds (/proc/PID/stat fields 14 and 15)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / TICK


class Writer:
    """The unit's frames into a can-log, on the unit's schedule, lines appended whole."""

    def __init__(self, path: Path, flap: bool) -> None:
        self.path = path
        self.flap = flap  # every ESTOP_BRAKE a state change: the worst case for the pushes
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        brake_ctr = status_ctr = 0
        start = time.monotonic()
        n = 0
        try:
            while not self._stop.is_set():
                due = start + n / BRAKE_HZ
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                now = time.time()
                armed = (n if self.flap else n // 300) % 2  # a change every 3 s, or always
                data = BrakeFrame.for_state(State.ARMED if armed else State.STOPPED,
                                            Reason.NONE if armed else Reason.TCP_STOP,
                                            counter=brake_ctr).encode()
                lines = [format_line(CanLogRecord.at(now, "estop", 0x050, data))]
                brake_ctr = (brake_ctr + 1) % 15
                if n % (BRAKE_HZ // STATUS_HZ) == 0:
                    data = StatusFrame(50, 0, 0, 0, 20, status_ctr).encode()
                    lines.append(format_line(CanLogRecord.at(now, "estop", 0x051, data)))
                    status_ctr = (status_ctr + 1) % 15
                for line in lines:  # one write per line, as estopd writes them
                    os.write(fd, (line + "\n").encode())
                self.frames += len(lines)
                n += 1
        finally:
            os.close(fd)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def start_dashboard(can_log: Path) -> tuple[subprocess.Popen[str], str]:
    proc = subprocess.Popen([sys.executable, "-m", "estop", "dashboard", "--can-log",
                             str(can_log), "--listen", "127.0.0.1:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
    if m is None:
        proc.kill()
        raise SystemExit(f"estop dashboard did not start: {line!r}")
    return proc, m[1]


def start_peer(can_log: Path) -> tuple[subprocess.Popen[bytes], subprocess.Popen[bytes]]:
    tail = subprocess.Popen(["tail", "-n", "+1", "-f", str(can_log)], stdout=subprocess.PIPE)
    mon = subprocess.Popen([sys.executable, "-m", "estop", "monitor", "--log", "-", "--quiet"],
                           stdin=tail.stdout, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    return tail, mon


def run(seconds: float, flap: bool, chromium: str) -> dict[str, object]:
    """One measurement: the dashboard following the writer, the page open in chromium."""
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="estop-dash-bench-") as tmp:
        can_log = Path(tmp) / "can.log"
        can_log.touch()
        writer = Writer(can_log, flap)
        writer.start()
        dash, url = start_dashboard(can_log)
        tail, peer = start_peer(can_log)
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                             args=["--no-sandbox"])
                try:
                    page = browser.new_page()
                    page.goto(url)
                    page.wait_for_function("window.estopUpdates > 2")
                    time.sleep(1.0)  # warmed up
                    cpu0, peer0, t0 = cpu_seconds(dash.pid), cpu_seconds(peer.pid), \
                        time.monotonic()
                    frames0 = writer.frames
                    per_second: list[int] = []
                    last = int(page.evaluate("window.estopUpdates"))
                    next_t = t0 + 1.0
                    while next_t <= t0 + seconds + 1e-9:
                        time.sleep(max(0.0, next_t - time.monotonic()))
                        now_count = int(page.evaluate("window.estopUpdates"))
                        per_second.append(now_count - last)
                        last = now_count
                        next_t += 1.0
                    wall = time.monotonic() - t0
                    stamps = page.evaluate("window.estopUpdateTimes")
                    cpu = (cpu_seconds(dash.pid) - cpu0) / wall * 100
                    peer_cpu = (cpu_seconds(peer.pid) - peer0) / wall * 100
                    frames = writer.frames - frames0
                finally:
                    browser.close()
        finally:
            writer.stop()
            for p in (dash, peer, tail):
                p.terminate()
            for p in (dash, peer, tail):
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    p.kill()
    return {"scenario": "every frame a state change" if flap else "a state change every 3 s",
            "seconds": round(wall, 2), "frames_per_s": round(frames / wall, 1),
            "server_cpu_percent": round(cpu, 2), "peer_monitor_cpu_percent": round(peer_cpu, 2),
            "updates_per_s_mean": round(sum(per_second) / len(per_second), 1),
            "updates_per_s_max": max(per_second),
            # the busiest second anywhere: by the page's clock as they came, by the server's as
            # they were sent
            "received_max_in_1s": busiest([r / 1000 for r, _ in stamps]),
            "sent_max_in_1s": busiest([s for _, s in stamps if s is not None])}


def busiest(times: list[float]) -> int:
    """The most of ``times`` (seconds) in any window of one second, [t, t + 1)."""
    times = sorted(times)
    best, lo = 0, 0
    for hi, t in enumerate(times):
        while t - times[lo] >= 1.0:
            lo += 1
        best = max(best, hi - lo + 1)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0,
                    help="measured time of each scenario (default 20)")
    args = ap.parse_args()
    chromium = shutil.which("chromium")
    if chromium is None:
        print("chromium missing: scripts/ensure-debs browser", file=sys.stderr)
        return 2
    runs = [run(args.seconds, flap, chromium) for flap in (False, True)]
    load = os.getloadavg()
    OUT.mkdir(exist_ok=True)
    (OUT / "dashboard_load.json").write_text(json.dumps(
        {"runs": runs, "goal_cpu_percent": GOAL_CPU, "goal_updates_per_s": GOAL_UPDATES,
         "load_average": [round(x, 2) for x in load], "cores": os.cpu_count()},
        indent=1) + "\n")
    ok = True
    print(f"dashboard load: {BRAKE_HZ} ESTOP_BRAKE + {STATUS_HZ} ESTOP_STATUS frames a second "
          f"into a can-log, the page open in chromium; machine: {os.cpu_count()} cores, load "
          f"average {load[0]:.2f}")
    for r in runs:
        cpu, upd = float(r["server_cpu_percent"]), int(r["received_max_in_1s"])  # type: ignore[arg-type]
        ok &= cpu < GOAL_CPU and upd <= GOAL_UPDATES
        print(f"  {r['scenario']} ({r['frames_per_s']} frames/s for {r['seconds']} s):")
        print(f"    server CPU          {cpu:6.2f} % of one core   goal < {GOAL_CPU:g} %   "
              f"{'ok' if cpu < GOAL_CPU else 'MISSED'}")
        print(f"    peer: estop monitor {r['peer_monitor_cpu_percent']:6.2f} % of one core   "
              f"(tail -f | estop monitor --log -: the same decoding, no web side)")
        print(f"    browser updates     {r['updates_per_s_mean']:6.1f} /s mean; the busiest "
              f"second: {upd} received, {r['sent_max_in_1s']} sent   goal <= {GOAL_UPDATES}   "
              f"{'ok' if upd <= GOAL_UPDATES else 'MISSED'}")
    print(f"  written to {OUT / 'dashboard_load.json'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
