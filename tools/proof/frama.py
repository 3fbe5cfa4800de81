"""Where the core and the proof files are, and how Frama-C is run on them."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "firmware" / "core"
PROVE = ROOT / "prove"
BUILD = ROOT / "build" / "prove"
TOOLS = ("frama-c", "why3", "z3", "cvc4")


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


def frama_c(args: list[str], log: Path, timeout: int, env: dict[str, str]) -> tuple[int, str]:
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        cwd = BUILD / "cwd"  # empty: quoted includes of an -include file look here first
        cwd.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(["frama-c", *args], capture_output=True, text=True,
                              timeout=timeout, env=env, cwd=cwd)
    except subprocess.TimeoutExpired:
        log.write_text(f"timed out after {timeout} s\n")
        return -1, f"timed out after {timeout} s"
    out = proc.stdout + proc.stderr
    log.write_text(out + f"\n[prove] wall time {time.monotonic() - t0:.0f} s\n")
    return proc.returncode, out + f"\n[prove] wall time {time.monotonic() - t0:.0f} s\n"


def frama_c_until(args: list[str], log: Path, timeout: int, env: dict[str, str],
                  stop: re.Pattern[str]) -> tuple[int, str, bool]:
    """frama_c, stopped at the first line of its output that matches stop (the self-test's
    mutants: one failed goal is enough, the rest of the run would only cost time). True when
    it was stopped so."""
    log.parent.mkdir(parents=True, exist_ok=True)
    cwd = BUILD / "cwd"
    cwd.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    lines: list[str] = []
    stopped = False
    with subprocess.Popen(["frama-c", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, env=env, cwd=cwd, start_new_session=True) as proc:
        assert proc.stdout is not None
        try:
            for line in proc.stdout:
                lines.append(line)
                if stop.search(line) or time.monotonic() - t0 > timeout:
                    stopped = bool(stop.search(line))
                    break
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)  # frama-c and its solvers
            rc = proc.wait()
    out = "".join(lines) + f"\n[prove] wall time {time.monotonic() - t0:.0f} s\n"
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
    env = dict(os.environ)
    env["WHY3CONFIG"] = str(conf)
    return env
