"""Eva on prove/eva_driver.c: alarms, the functions reached, and the driver's rules.

The driver states rules of the state machine as assertions named rule_* after the calls (an
entry point that leaves STOPPED where it must not). Eva must find each one valid in each run:
an assertion it cannot show, or one it never reaches, fails the run.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from .frama import BUILD, PROVE, ROOT, core_functions, core_sources, cpp_args, cpu_time, frama_c

EVA_TIMEOUT_S = 1200  # the keyed run took 322 s beside make test's other steps (149 s idle, then)
# Eva's precision: meta-option level 2, and loops up to 1024 iterations unrolled (the
# zeroing of estop_core_t in estop_init is ~1000 byte stores; merged iterations would make
# every field "maybe uninitialised").
EVA_OPTS = ["-eva-precision", "2", "-eva-auto-loop-unroll", "1024", "-eva-split-return", "auto",
            "-eva-print-callstacks"]
DRIVER = PROVE / "eva_driver.c"
# make prove's two runs: (name, keyed, whole_chunks). Both try TCP chunks of every length
# 0..49 (the driver's exact_call). Until issue 24's thirty-third round the run without a key
# tried whole frames only, to save time (every length cost the keyed run 100 of its 149 s);
# since the driver's loop passes any length in one array and tries each length in an array
# of its own once, after the loop, the two runs take 68 s and 48 s (idle machine; 155 s and
# about 50 s before, the second with whole frames; whole frames 39 s with this driver), the
# same statements reached.
RUNS = (("keyed", 1, False), ("plain", 0, False))
# The driver's loop makes 9 calls (its case numbers 0..8), one bit each (DRIVER_CASES there).
ALL_CALLS = 0x1FF


@dataclasses.dataclass
class EvaResult:
    name: str
    alarms: list[str]
    functions: dict[str, tuple[int, int]]  # reached statements, all statements
    unreached: list[str]
    log: Path
    error: str = ""
    unknown_props: int = 0
    invalid: list[str] = dataclasses.field(default_factory=list)  # annotations found false
    rules: dict[str, str] = dataclasses.field(default_factory=dict)  # rule -> Eva's status
    cpu_s: float = 0.0  # frama-c's (frama.cpu_time)

    @property
    def rules_not_shown(self) -> list[str]:
        return sorted(f"{r} ({s})" for r, s in self.rules.items() if s != "Valid")


def driver_rules(driver: Path = DRIVER) -> list[str]:
    """The names of the driver's rule assertions."""
    return sorted(set(re.findall(r"assert (rule_\w+):", driver.read_text())))


def rule_statuses(out: str, rules: list[str]) -> dict[str, str]:
    """Each rule's status in the -report part of a log: Valid, Dead, Unknown or Invalid; a rule
    the report does not name has status 'missing'."""
    found = {r: "missing" for r in rules}
    for m in re.finditer(r"^\[\s*([^\]]*?)\s*\] Assertion '(rule_\w+)'", out, re.M):
        if m.group(2) in found:
            word = m.group(1)
            found[m.group(2)] = {"-": "Unknown"}.get(word, word)
    return found


def helper_name(name: str, functions: set[str]) -> str:
    """The function a name of Eva's stands for: Frama-C numbers each file's copy of a static
    inline helper (rd_u32le_3 is a copy of rd_u32le), by the order of the files; any other
    name is itself."""
    base = re.sub(r"_\d+$", "", name)
    return base if base in functions else name


def copies_unnumbered(text: str, functions: set[str]) -> str:
    """text with each copy of a helper named as the helper (helper_name): a self-test plant
    names the helper alone (estop_udp.c split off estop_core.c made rd_u32le_0 of the planted
    datagram read rd_u32le_3)."""
    return re.sub(r"\b[A-Za-z_]\w*\b", lambda m: helper_name(m.group(0), functions), text)


def run_eva(name: str, core_dir: Path, keyed: int, env: dict[str, str],
            calls: int = ALL_CALLS, whole_chunks: bool = False) -> EvaResult:
    """Eva over the driver; calls: the driver's calls it makes (a self-test copy's few);
    whole_chunks: TCP chunks of one whole frame only (a self-test copy's)."""
    log = BUILD / f"eva-{name}.log"
    args = [*cpp_args(core_dir, f"-DDRIVER_KEYED={keyed}", f"-DDRIVER_CASES={calls:#x}u",
                           f"-DDRIVER_TCP_WHOLE={int(whole_chunks)}"),
            str(DRIVER),
            *map(str, core_sources(core_dir)), "-eva", *EVA_OPTS,
            "-then", "-metrics", "-metrics-eva-cover", "-then", "-report"]
    rc, out = frama_c(args, log, EVA_TIMEOUT_S, env)
    res = EvaResult(name, [], {}, [], log, cpu_s=cpu_time(log))
    if rc != 0 or "ANALYSIS SUMMARY" not in out:
        res.error = f"frama-c failed (exit {rc}); see {log.relative_to(ROOT)}"
        return res
    lines = out.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("[eva:alarm]"):
            where = line.split("]", 1)[1].split(": Warning", 1)[0].strip()
            where = where.replace(str(ROOT) + "/", "")
            j = i + 1
            what = line.split(": Warning:", 1)[1].strip() if ": Warning:" in line else ""
            while j < len(lines) and lines[j].startswith(" ") and "stack:" not in lines[j]:
                what += (" " if what else "") + lines[j].strip()
                j += 1
            if "assertion 'rule_" in what:
                continue  # a rule of the driver: judged by its status below
            if "got status unknown" in what or (
                    "got status invalid" in what and "Behavior may be inactive" in what):
                # An ACSL property Eva cannot decide: WP proves it. A behavior's clause that
                # Eva finds false only where it cannot tell whether the behavior is active (its
                # assumes merged with the other behavior's) is undecided too, not false.
                res.unknown_props += 1
            elif "got status invalid" in what:
                res.error = f"Eva finds an annotation false: {where}: {what}"
                res.invalid.append(f"{where}: {what}")
            else:
                res.alarms.append(f"{where}: {what}")
    res.rules = rule_statuses(out, driver_rules())
    # Eva also meets the ACSL annotations (WP proves them); one it finds false is a failure.
    for m in re.finditer(r"^\s+(\w+)\s+(\d+) valid\s+(\d+) unknown\s+(\d+) invalid", out, re.M):
        if int(m.group(4)) > 0:
            res.error = f"{m.group(4)} {m.group(1).lower()} found invalid by Eva"
    m = re.search(r"(\d+) alarms? generated", out)
    if m is None and "No alarm" not in out and res.alarms:
        res.error = res.error or "no alarm count in the summary"
    if m and int(m.group(1)) != len(res.alarms):
        res.error = f"summary says {m.group(1)} alarms, the log lists {len(res.alarms)}"
    for m in re.finditer(r"^  (\w+): (\d+) stmts out of (\d+)", out, re.M):
        res.functions[m.group(1)] = (int(m.group(2)), int(m.group(3)))
    # A helper counts under its own name (helper_name), reached when any copy is.
    wanted = core_functions(core_dir)
    merged: dict[str, tuple[int, int]] = {}
    for fn, (reached, total) in res.functions.items():
        base = helper_name(fn, wanted)
        old = merged.get(base, (0, 0))
        merged[base] = (max(old[0], reached), max(old[1], total))
    res.functions = merged
    if not res.functions or not wanted:
        res.error = res.error or "no coverage figures in the log"
    res.unreached = sorted(f for f in wanted if res.functions.get(f, (0, 1))[0] == 0)
    return res
