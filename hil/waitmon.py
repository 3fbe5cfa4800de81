"""Run-queue wait monitor: when was the daemon ready to run, and not let?

    python waitmon.py PIDFILE OUTFILE

Under TCG the harness runs the daemon as an ordinary process (hil/run), so the guest's own
scheduler may hold it back behind the harness's busy processes, which a deployed daemon at
SCHED_FIFO 50 never waits for. The kernel counts that time per thread: the second field of
/proc/PID/schedstat, nanoseconds runnable on a run queue but not running. At real-time priority
(SCHED_FIFO 60, as stallmon.py) this samples the daemon's main thread (its loop; PIDFILE holds
its pid, rewritten at each start) every 10 ms and writes each interval in which that wait grew
by more than 1 ms, as ``start end`` wall-clock seconds, ending at the sample and as long as the
growth. The kernel adds a wait when it ends (when the thread runs), so a wait ended within the
10 ms before the sample (more when this monitor itself was held) and began that long before
its end: the interval is off by that much, which the judges' 25 ms of runnable time in a
50 ms gap allow for. Time in which the daemon slept, blocked or ran is never written: a
daemon that sends nothing because it waits for the wrong time, blocks on a write or spins is
judged as before (tests/harness/test_hil_waitmon.py).
"""

from __future__ import annotations

import os
import sys
import time

from stallmon import start

# Every 10 ms, not every 2 as stallmon.py: under TCG each wake-up of a Python process costs a
# fraction of a ms of the guest's CPU, and sampled every 2 ms this woke as often as the two
# stall monitors together (the first run with it fell short of a flood: 4,625 datagrams/s).
PERIOD_S = 0.010
REPORT_S = 0.001  # a growth of the wait beyond this is written
PID_EVERY = 5  # samples between two reads of PIDFILE (50 ms); at once when the pid is gone


def read_pid(path: str) -> int | None:
    try:
        with open(path) as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


class Schedstat:
    """A thread's /proc/PID/schedstat, kept open and read again from its start at each sample
    (an open, a read and a close every 10 ms cost the most of this monitor's time under TCG)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.fd: int | None = None

    def run_wait_s(self) -> float | None:
        """The thread's time on a run queue so far (seconds), None when it is gone."""
        try:
            if self.fd is None:
                self.fd = os.open(f"/proc/{self.pid}/schedstat", os.O_RDONLY)
            return int(os.pread(self.fd, 128, 0).split()[1]) / 1e9
        except (OSError, ValueError, IndexError):
            self.close()
            return None

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def main() -> int:
    pidfile = sys.argv[1]
    out = start(sys.argv[2], "waits")  # stallmon.py's: SCHED_FIFO 60, the header, SIGTERM
    pid: int | None = None
    stat: Schedstat | None = None
    prev_wait: float | None = None
    n = 0
    while True:
        time.sleep(PERIOD_S)
        if pid is None or n % PID_EVERY == 0:
            new = read_pid(pidfile)
            if new != pid:
                pid, prev_wait = new, None  # a new daemon: no growth to take yet
                if stat is not None:
                    stat.close()
                stat = Schedstat(pid) if pid is not None else None
        n += 1
        now = time.time()
        wait = stat.run_wait_s() if stat is not None else None
        if wait is None:
            pid = None
        elif prev_wait is not None and wait - prev_wait > REPORT_S:
            out.write(f"{now - (wait - prev_wait):.6f} {now:.6f}\n")
        prev_wait = wait


if __name__ == "__main__":
    sys.exit(main())
