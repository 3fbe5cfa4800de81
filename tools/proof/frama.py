"""Where the core and the proof files are, and how Frama-C is run on them."""

from __future__ import annotations

import ctypes
import os
import re
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "firmware" / "core"
PROVE = ROOT / "prove"
BUILD = ROOT / "build" / "prove"
SOLVERS = ROOT / "tools" / "proof" / "solvers"  # the solvers as Why3 runs them (cpu-limited)
TOOLS = ("frama-c", "why3", "z3", "cvc4", "ocamlopt")  # ocamlopt: task_idle.py
# The CPU time of every Frama-C run of this process, in order, by its log's name (frama-c,
# why3server and the solvers). make prove prints what each analysis cost beside its wall time,
# which beside make test's other steps says little of the work (issue 24). Frama-C runs its
# solvers through why3server, and a run is ended by killing its process group: why3server,
# orphaned, was reaped by init with the solvers it had reaped, so a run stopped at its first
# failure (a self-test mutant) counted 3 of its 17 s (issue 24's fifty-first round). While a
# run is on, this process is their subreaper (prctl): it reaps them and counts their time.
CPU_RUNS: list[tuple[str, float]] = []
_CPU_LOCK = threading.Lock()
_PR_SET_CHILD_SUBREAPER = 36
_SUBREAPER_LOCK = threading.Lock()
_subreaper_runs = 0  # the runs on: this process is the subreaper while any is


def cpu_time(log: Path) -> float:
    """The CPU time of the last run that wrote log (0 if none did)."""
    with _CPU_LOCK:
        return next((cpu for name, cpu in reversed(CPU_RUNS) if name == log.name), 0.0)


def core_sources(core_dir: Path) -> list[Path]:
    return sorted(core_dir.glob("*.c"))


def core_files(core_dir: Path) -> list[Path]:
    """The sources and the headers (the private header defines static inline helpers)."""
    return sorted([*core_dir.glob("*.c"), *core_dir.glob("*.h")])


def core_functions(core_dir: Path) -> set[str]:
    """Every function defined in the core's .c files (a definition starts a line)."""
    names = set()
    pat = re.compile(r"^(?:static\s+)?(?:inline\s+)?(?:const\s+)?[A-Za-z_][\w ]*?[\s*]"
                     r"([A-Za-z_]\w*)\([^;]*$")
    for src in core_files(core_dir):
        for line in src.read_text().splitlines():
            m = pat.match(line)
            if m and not line.startswith(("#", " ", "\t", "/*", "*")):
                names.add(m.group(1))
    return names


def _subreaper(on: bool) -> None:
    """Counted per run: the first run on makes this process the subreaper of the orphans below
    it, the last one off gives that up (a pytest process outside the runs adopts nothing)."""
    global _subreaper_runs
    with _SUBREAPER_LOCK:
        _subreaper_runs += 1 if on else -1
        if _subreaper_runs == (1 if on else 0):
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0) != 0:
                raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")


def _group(pgid: int) -> list[tuple[int, int]]:
    """(pid, parent pid) of the processes of a process group, zombies too."""
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                stat = Path(entry.path, "stat").read_text()
            except OSError:
                continue  # gone meanwhile
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid:
                found.append((int(entry.name), int(fields[1])))
    return found


def _reap_group(pgid: int, limit_s: float = 10.0) -> float:
    """The CPU time of the processes of a killed group that this process adopted (its
    subreaper), with what they had reaped; each reaped here as it comes, until none is left
    (or limit_s passed: a process held in the kernel stays)."""
    cpu = 0.0
    end = time.monotonic() + limit_s
    while (left := _group(pgid)) and time.monotonic() < end:
        adopted = [pid for pid, parent in left if parent == os.getpid()]
        for pid in adopted:
            try:
                _, _, usage = os.wait4(pid, 0)  # killed: it ends at once
            except ChildProcessError:
                continue
            cpu += usage.ru_utime + usage.ru_stime
        if not adopted:
            time.sleep(0.005)  # a parent still dying: its orphans come here after it
    return cpu


def frama_c(args: list[str], log: Path, timeout: int, env: dict[str, str]) -> tuple[int, str]:
    """Frama-C run to its end (or killed, with its solvers, after timeout s: exit -1)."""
    rc, out, _ = frama_c_until(args, log, timeout, env, None)
    return rc, out


def frama_c_until(args: list[str], log: Path, timeout: int, env: dict[str, str],
                  stop: re.Pattern[str] | None) -> tuple[int, str, bool]:
    """Frama-C with its output in log (and the wall time after it), stopped at the first line
    that matches stop (the self-test's mutants: one failed goal is enough, the rest of the run
    would only cost time), and killed with its solvers after timeout s, output or not. The
    exit status (-1 on the timeout), the output, and whether stop matched."""
    log.parent.mkdir(parents=True, exist_ok=True)
    cwd = BUILD / "cwd"  # empty: quoted includes of an -include file look here first
    cwd.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    lines: list[str] = []
    stopped = False
    # The temporary files of frama-c and its solvers in a directory of the run's own, removed
    # after it: a frama-c killed (a mutant's first failure, a timeout) leaves its preprocessed
    # annotations (cppannot*.c, one per source file): 7 in /tmp for each such run before.
    # stderr after stdout, as the parsers read it (an error line never splits an alarm's)
    _subreaper(True)
    try:
        with tempfile.TemporaryDirectory(prefix="tmp-", dir=log.parent,
                                         ignore_cleanup_errors=True) as scratch, \
                tempfile.TemporaryFile("w+") as err, subprocess.Popen(
                ["frama-c", *args], stdout=subprocess.PIPE, stderr=err, text=True,
                env=dict(env, TMPDIR=scratch), cwd=cwd, start_new_session=True) as proc:

            def kill() -> None:
                # frama-c and its solvers. Not through proc.poll(), which would reap frama-c and
                # lose its CPU time; a group whose leader is a zombie is still there to signal.
                if proc.returncode is None:
                    try:
                        os.killpg(proc.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass

            timer = threading.Timer(timeout, kill)
            timer.start()
            assert proc.stdout is not None
            try:
                for line in proc.stdout:
                    lines.append(line)
                    if stop is not None and stop.search(line):
                        stopped = True
                        break
            finally:
                timer.cancel()
                kill()
                # wait4: the exit status and the CPU time of frama-c with what it reaped, then
                # of what it left (why3server, a solver), adopted here
                _, status, usage = os.wait4(proc.pid, 0)
                proc.returncode = rc = os.waitstatus_to_exitcode(status)
                cpu = usage.ru_utime + usage.ru_stime + _reap_group(proc.pid)
            with _CPU_LOCK:
                CPU_RUNS.append((log.name, cpu))
            err.seek(0)
            lines.append(err.read())
    finally:
        _subreaper(False)
    if not stopped and time.monotonic() - t0 >= timeout:
        rc = -1
        lines.append(f"timed out after {timeout} s\n")
    out = "".join(lines) + (f"\n[prove] wall time {time.monotonic() - t0:.0f} s, CPU time "
                            f"{cpu:.0f} s\n")
    log.write_text(out)
    return rc, out, stopped


def cpp_args(core_dir: Path, *defines: str) -> list[str]:
    """Eva reads the predicates only; WP the contracts as well (a defines entry)."""
    extra = [f"-I{core_dir}", f"-I{PROVE}", f"-include {PROVE / 'builtins.h'}",
             f"-include {PROVE / 'predicates.h'}", *defines]
    return ["-machdep", "x86_64", "-cpp-extra-args=" + " ".join(extra)]


def why3_env() -> dict[str, str]:
    """A Why3 configuration of our own (the solvers this machine has), not the user's."""
    conf = BUILD / "why3.conf"
    if not conf.exists():
        BUILD.mkdir(parents=True, exist_ok=True)
        subprocess.run(["why3", "config", "detect", "-C", str(conf)], check=True,
                       capture_output=True, text=True, timeout=120)
        # No memory limit: the goals are small, and a limit turns a solver's large virtual
        # reservation into a failure.
        conf.write_text(re.sub(r"(?m)^memlimit = \d+", "memlimit = 0", conf.read_text()))
    # Each solver through its CPU-time bound (tools/proof/solvers/cpu-limited), which runs the
    # solver of that name from PATH: a conf detected before it was there is mended too.
    # Written only when it changes, and whole (a rename): make prove's workers call this while
    # other runs' frama-c read the file.
    before = conf.read_text()
    text = before
    for name in ("cvc4", "z3"):
        text = re.sub(r'(?m)^path = "[^"]*/' + name + '"$', f'path = "{SOLVERS / name}"', text)
    if text != before:
        tmp = conf.with_name(conf.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(conf)
    env = dict(os.environ)
    env["WHY3CONFIG"] = str(conf)
    return env
