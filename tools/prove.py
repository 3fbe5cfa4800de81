"""`make prove`: the firmware core under Frama-C (docs/PROOF.md).

1. Eva: prove/eva_driver.c calls every entry point in any order with unknown inputs, once for
   a unit with a key and once for one without. Every alarm fails the run; so does a function of
   firmware/core that the driver does not reach. Prints the alarms, the functions and the
   statements reached.
2. WP: the ACSL contracts of firmware/core (per function, in parallel runs), proved by Qed (WP's
   own simplifier) and the SMT solvers through Why3. Every goal must be proved.
3. Self-test: the same analyses on copies of the core with a planted fault each (an
   out-of-bounds write, a wrong release path); each must fail, or the set-up is broken (a
   missing prover, a driver that no longer reaches the code, a contract that says nothing) and
   so is the run.
Exit status 0 when all three hold.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "firmware" / "core"
PROVE = ROOT / "prove"
BUILD = ROOT / "build" / "prove"
TOOLS = ("frama-c", "why3", "z3", "cvc4")
PROVERS = "z3,cvc4"
EVA_TIMEOUT_S = 600
WP_TIMEOUT_S = 600
# Eva's precision: meta-option level 2, and loops up to 1024 iterations unrolled (the
# zeroing of estop_core_t in estop_init is ~1000 byte stores; merged iterations would make
# every field "maybe uninitialised").
EVA_OPTS = ["-eva-precision", "2", "-eva-auto-loop-unroll", "1024", "-eva-split-return", "auto",
            "-eva-print-callstacks"]
# Caveat: WP's memory model in which the pointers a function receives are assumed separated
# and valid. Those hypotheses are not checked (-wp-check-memory-model is not passed: some are
# false, docs/PROOF.md "Known holes", issue 24).
# A slot's fill is bounded by a quantified invariant (slots_ok): Qed instantiates it for the 8
# slots. The timeout leaves the slowest goal (about 16 s on an idle 2-core machine) room on a
# loaded one; a run on a machine busy with other work timed out at 20 s.
WP_MODEL = "Caveat"
# A run under Typed also checks the hypotheses of its model at every call and runs smoke tests
# (a precondition that cannot hold or code the proof finds dead fails the run).
MODEL_CHECKS = {"Typed": ["-wp-check-memory-model", "-wp-smoke-tests"]}
MODEL_TAGS = {"Typed": "typed_", "Caveat": "typed_caveat_"}  # how WP names their goals
WP_OPTS = ["-wp-prover", PROVERS, "-wp-par", "2",
           "-wp-bound-forall-unfolding", "8"]
GOAL_TIMEOUT_S = 40
# A run that leaves goals unproved at GOAL_TIMEOUT_S (CI's machine, busy, timed one out at 40 s)
# is run once more with this per-goal timeout; the output says so. Still a proof: only the
# time the solvers get changes.
GOAL_RETRY_TIMEOUT_S = 150
WP_CACHE = BUILD / "wp-cache"


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


@dataclasses.dataclass
class WpResult:
    name: str
    proved: int
    total: int
    by_prover: dict[str, int]
    failed: list[str]
    log: Path
    error: str = ""
    smoke: int = 0  # smoke tests checked (Typed runs)
    smoke_failed: list[str] = dataclasses.field(default_factory=list)
    wrong_model: list[str] = dataclasses.field(default_factory=list)


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


def cpp_args(core_dir: Path, *defines: str) -> list[str]:
    """Eva reads the predicates only; WP the contracts as well (a defines entry)."""
    extra = [f"-I{core_dir}", f"-I{PROVE}", f"-include {PROVE / 'builtins.h'}",
             f"-include {PROVE / 'predicates.h'}", *defines]
    return ["-machdep", "x86_64", "-cpp-extra-args=" + " ".join(extra)]


def run_eva(name: str, core_dir: Path, keyed: int, env: dict[str, str]) -> EvaResult:
    log = BUILD / f"eva-{name}.log"
    args = [*cpp_args(core_dir, f"-DDRIVER_KEYED={keyed}"), str(PROVE / "eva_driver.c"),
            *map(str, core_sources(core_dir)), "-eva", *EVA_OPTS,
            "-then", "-metrics", "-metrics-eva-cover"]
    rc, out = frama_c(args, log, EVA_TIMEOUT_S, env)
    res = EvaResult(name, [], {}, [], log)
    if rc != 0 or "ANALYSIS SUMMARY" not in out:
        res.error = f"frama-c failed (exit {rc}); see {log.relative_to(ROOT)}"
        return res
    lines = out.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("[eva:alarm]"):
            where = line.split("]", 1)[1].split(": Warning", 1)[0].strip()
            where = where.replace(str(ROOT) + "/", "")
            j = i + 1
            what = ""
            while j < len(lines) and lines[j].startswith(" ") and "stack:" not in lines[j]:
                what += (" " if what else "") + lines[j].strip()
                j += 1
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
    # Frama-C renames the copies of a static inline helper in each file (rd_u32le_0, ...):
    # a helper counts under its own name, reached when any copy is.
    merged: dict[str, tuple[int, int]] = {}
    for fn, (reached, total) in res.functions.items():
        base = re.sub(r"_\d+$", "", fn) if re.sub(r"_\d+$", "", fn) in core_functions(core_dir) \
            else fn
        old = merged.get(base, (0, 0))
        merged[base] = (max(old[0], reached), max(old[1], total))
    res.functions = merged
    wanted = core_functions(core_dir)
    if not res.functions or not wanted:
        res.error = res.error or "no coverage figures in the log"
    res.unreached = sorted(f for f in wanted if res.functions.get(f, (0, 1))[0] == 0)
    return res


# WP runs, each on a group of functions of the core, all in one go where a group is quick.
# The kernel inlines the small loop-free helpers (prove/wp_inline.txt) into their callers, so
# the state machine's properties are proved on the code as it runs, not on hand-written
# summaries of each helper.
def wp_groups() -> list[tuple[str, list[str]]]:
    """name: functions [-property ...]; a -property is left out of the run: a clause the
    solvers did not prove, listed in docs/PROOF.md (printed by every run, never hidden)."""
    groups = []
    for raw in (PROVE / "wp_groups.txt").read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            name, fcts = line.split(":", 1)
            groups.append((name.strip(), fcts.split()))
    return groups


def inline_list() -> str:
    names = []
    for raw in (PROVE / "wp_inline.txt").read_text().splitlines():
        names += raw.split("#", 1)[0].split()
    return ",".join(names)


# Per-run WP options of prove/wp_groups.txt ("%name").
WP_FLAGS = {
    "split": ["-wp-split"],  # conjunctions and branches into sub-goals (mostly Qed's then)
}


def run_wp(name: str, core_dir: Path, fcts: list[str], env: dict[str, str],
           goal_timeout_s: int = GOAL_TIMEOUT_S, cache: bool = False) -> WpResult:
    log = BUILD / f"wp-{name}.log"
    names = [f for f in fcts if not f.startswith(("-", "+", "@", "%"))]
    left_out = [f for f in fcts if f.startswith("-")]
    only = [f[1:] for f in fcts if f.startswith("+")]
    models = [f[1:] for f in fcts if f.startswith("@")]
    flags = [opt for f in fcts if f.startswith("%") for opt in WP_FLAGS[f[1:]]]
    model = models[0] if models else WP_MODEL
    args = [*cpp_args(core_dir, f"-include {PROVE / 'contracts.h'}"),
            *map(str, core_sources(core_dir)),
            "-inline-calls", inline_list(), "-wp", "-wp-fct", ",".join(names),
            # One model a run: a second -wp-model is added to the first, not put in its place
            # (Typed and Caveat together named the goals typed_caveat_*).
            "-wp-model", model, *WP_OPTS, *MODEL_CHECKS.get(model, []),
            "-wp-timeout", str(goal_timeout_s), *flags]
    if cache:
        # The solvers' verdicts by goal (a hash of the goal and the prover): a run again with
        # a longer timeout re-tries only what timed out. Emptied by every make prove.
        args += ["-wp-cache", "update", "-wp-cache-dir", str(WP_CACHE / name)]
    if left_out or only:
        args.append("-wp-prop=" + ",".join(only + left_out))
    rc, out = frama_c(args, log, WP_TIMEOUT_S, env)
    res = WpResult(name, 0, 0, {}, [], log)
    m = re.search(r"Proved goals:\s+(\d+)\s*/\s*(\d+)", out)
    if rc != 0 or m is None:
        res.error = f"frama-c failed (exit {rc}); see {log.relative_to(ROOT)}"
        tail = [x for x in out.splitlines() if "Error" in x or "error" in x][:5]
        if tail:
            res.error += ": " + " | ".join(tail)
        return res
    res.proved, res.total = int(m.group(1)), int(m.group(2))
    for pm in re.finditer(r"^\s+(Qed|Z3[^:]*|CVC4[^:]*|Alt-Ergo[^:]*|Terminating|Unreachable)"
                          r":\s+(\d+)", out[m.end():], re.M):
        prover = pm.group(1).split()[0]
        res.by_prover[prover] = res.by_prover.get(prover, 0) + int(pm.group(2))
    for fm in re.finditer(r"^\[wp\] \[(?:Timeout|Unknown|Failed|Stepout)[^\]]*\] Goal (\S+)",
                          out, re.M):
        res.failed.append(fm.group(1))
    for fm in re.finditer(r"^\[wp\] Goal (\S+) : (?!Valid)", out, re.M):
        res.failed.append(fm.group(1))
    parse_checks(res, out, model)
    return res


def parse_checks(res: WpResult, out: str, model: str) -> None:
    """The smoke tests of a run's log and the goals of another memory model than its own."""
    # A smoke test fails when the solvers prove \false at a point: a precondition that can
    # never hold, or code the proof finds dead (every goal after it would be proved vacuously).
    smoke: dict[str, bool] = {}
    for sm in re.finditer(r"^\[wp\] \[(Passed|Failed)\] Smoke-test (\S+)", out, re.M):
        smoke[sm.group(2)] = smoke.get(sm.group(2), True) and sm.group(1) == "Passed"
    res.smoke = len(smoke)
    res.smoke_failed = sorted(g for g, passed in smoke.items() if not passed)
    # Every goal carries the run's model and no other one (WP names them typed_* under Typed,
    # typed_caveat_* under Caveat: Typed with Caveat's hypotheses, which a run under Typed
    # alone must not get).
    tag = MODEL_TAGS[model]
    goals = set(re.findall(r"Goal (\w+)", out)) | set(smoke)
    res.wrong_model = sorted(g for g in goals if not g.startswith(tag) or any(
        g.startswith(tag + extra) for extra in ("caveat_", "ref_", "raw_")
        if extra not in tag))


def run_wp_retrying(name: str, fcts: list[str], env: dict[str, str]) -> tuple[list[str], WpResult]:
    """A run of the core's group, and once more with GOAL_RETRY_TIMEOUT_S a goal when goals
    were left unproved (the cache keeps what the first pass proved); the goals the first pass
    left unproved, and the last pass's result."""
    (WP_CACHE / name).mkdir(parents=True, exist_ok=True)
    first = run_wp(name, CORE, fcts, env, GOAL_TIMEOUT_S, cache=True)
    if not first.failed or first.error:
        return [], first
    return first.failed, run_wp(name, CORE, fcts, env, GOAL_RETRY_TIMEOUT_S, cache=True)


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


# ---- self-test: the same analyses must fail on a planted fault --------------------------------

@dataclasses.dataclass
class Plant:
    name: str
    file: str        # in firmware/core
    old: str         # text replaced (must occur exactly once)
    new: str
    check: str       # "eva" or "wp:<group>"
    expect: str      # an alarm (its text) or a goal (its name) that must then fail
    prop: str = ""   # wp: only this property is tried (the planted goal costs its timeout)


def plants() -> list[Plant]:
    out = []
    text = (PROVE / "planted.txt").read_text()
    for block in text.split("\n---\n"):
        fields: dict[str, str] = {}
        key = None
        for raw in block.splitlines():
            if raw.startswith("#"):
                continue
            m = re.match(r"^(name|file|check|expect|prop|old|new):\s?(.*)$", raw)
            if m:
                key = m.group(1)
                fields[key] = m.group(2)
            elif key in ("old", "new"):
                fields[key] += "\n" + raw
        if fields:
            out.append(Plant(fields["name"], fields["file"], fields["old"], fields["new"],
                             fields["check"], fields["expect"], fields.get("prop", "")))
    return out


def planted_copy(p: Plant) -> Path:
    dst = BUILD / f"planted-{p.name}"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(CORE, dst)
    target = dst / p.file
    src = target.read_text()
    if src.count(p.old) != 1:
        raise SystemExit(f"prove: error: self-test {p.name}: its planted site occurs "
                         f"{src.count(p.old)} times in {p.file} (want 1); update "
                         "prove/planted.txt")
    target.write_text(src.replace(p.old, p.new))
    return dst


def run_plant(p: Plant, env: dict[str, str]) -> tuple[Plant, bool, str]:
    """True when the planted fault was caught: the analysis reports the expected alarm or
    fails the expected goal (not merely fails somewhere)."""
    core_dir = planted_copy(p)
    if p.check == "eva":
        r = run_eva(f"planted-{p.name}", core_dir, 0, env)
        # An alarm, or an annotation Eva finds false (a helper's precondition at its call).
        hits = [a for a in r.alarms + r.invalid if p.expect in a]
        return p, bool(hits) and (not r.error or bool(r.invalid)), (
            hits[0] if hits else f"{len(r.alarms)} alarms, none '{p.expect}'"
            + (f" ({r.error})" if r.error else ""))
    parts = p.check.split(":")  # wp:GROUP or wp:GROUP:FUNCTION
    group, only_fct = parts[1], (parts[2] if len(parts) > 2 else "")
    fcts = dict(wp_groups())[group]
    if only_fct:  # the group's options on one of its functions
        fcts = [f for f in fcts if f.startswith(("@", "%"))] + [only_fct]
    if p.prop:
        fcts = [f for f in fcts if not f.startswith(("-", "+"))] + [f"+{p.prop}"]
    w = run_wp(f"planted-{p.name}", core_dir, fcts, env)
    hit = any(p.expect in g for g in w.failed + w.smoke_failed)
    return p, hit and not w.error, (f"{p.expect} not proved" if hit else
                                    f"{w.proved}/{w.total} proved, {p.expect} not among the "
                                    "failures") + (f" ({w.error})" if w.error else "")


# ---- main ----------------------------------------------------------------------------------

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="analyses run at once (default 2)")
    ap.add_argument("--only", choices=["eva", "wp", "self-test"], action="append",
                    help="run only these parts (repeatable)")
    ap.add_argument("--group", action="append", metavar="NAME",
                    help="with wp: run only these groups of prove/wp_groups.txt (repeatable)")
    args = ap.parse_args()
    parts = set(args.only or ["eva", "wp", "self-test"])
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        print(f"prove: error: missing {', '.join(missing)} (scripts/ensure-debs prove)",
              file=sys.stderr)
        return 2
    BUILD.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(WP_CACHE, ignore_errors=True)
    env = why3_env()
    t0 = time.monotonic()
    ok = True
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        evas = [pool.submit(run_eva, n, CORE, k, env) for n, k in (("keyed", 1), ("plain", 0))
                ] if "eva" in parts else []
        wps = [pool.submit(run_wp_retrying, n, f, env) for n, f in wp_groups()
               if not args.group or n in args.group] if "wp" in parts else []
        selftests = [pool.submit(run_plant, p, env) for p in plants()
                     ] if "self-test" in parts else []
        for fut in evas:
            r = fut.result()
            reached = sum(1 for f in r.functions.values() if f[0] > 0)
            stmts = sum(f[0] for f in r.functions.values())
            all_stmts = sum(f[1] for f in r.functions.values())
            core_fns = core_functions(CORE)
            core_reached = sum(1 for f in core_fns if r.functions.get(f, (0, 1))[0] > 0)
            core_st = sum(r.functions.get(f, (0, 0))[0] for f in core_fns)
            core_all = sum(r.functions.get(f, (0, 0))[1] for f in core_fns)
            print(f"prove: eva {r.name}: {len(r.alarms)} alarms; core functions reached "
                  f"{core_reached}/{len(core_fns)}, core statements reached {core_st}/"
                  f"{core_all} ({100.0 * core_st / max(core_all, 1):.1f} %); with the driver "
                  f"{reached} functions, {stmts}/{all_stmts} statements")
            for a in r.alarms:
                print(f"prove:   alarm: {a}")
            if r.unreached:
                print(f"prove:   not reached in this run: {' '.join(r.unreached)}")
            if r.error:
                print(f"prove:   error: {r.error}")
            ok = ok and not r.alarms and not r.error
        if evas:
            never = set(core_functions(CORE))
            for fut in evas:
                never &= set(fut.result().unreached)
            if never:
                print(f"prove: eva: core functions no run reached: {' '.join(sorted(never))}")
            ok = ok and not never
        totals: dict[str, int] = {}
        for fut in wps:
            retried, w = fut.result()
            if retried:
                print(f"prove: wp {w.name}: {len(retried)} goals not proved with "
                      f"{GOAL_TIMEOUT_S} s each ({' '.join(retried)}); run again with "
                      f"{GOAL_RETRY_TIMEOUT_S} s each")
            for k, v in w.by_prover.items():
                totals[k] = totals.get(k, 0) + v
            provers = ", ".join(f"{k} {v}" for k, v in sorted(w.by_prover.items()))
            secs = re.search(r"wall time (\d+) s", w.log.read_text()) if w.log.exists() else None
            model = next((f[1:] for f in dict(wp_groups())[w.name] if f.startswith("@")),
                         WP_MODEL)
            checks = (f"; {w.smoke} smoke tests, {len(w.smoke_failed)} failed; memory-model "
                      "hypotheses checked at the calls" if model in MODEL_CHECKS else
                      "; no smoke tests, hypotheses not checked")
            print(f"prove: wp {w.name} ({model}): {w.proved}/{w.total} goals proved ({provers})"
                  + checks + (f"; {secs.group(1)} s" if secs else ""))
            groups = dict(wp_groups())
            left_out = [f[1:] for f in groups[w.name] if f.startswith("-")]
            # A property left out of this run may be the only one of another run (+property)
            # over the same functions: proved there, with other options.
            elsewhere = {f"-{p}": n for n, fs in groups.items() if n != w.name
                         for p in (x[1:] for x in fs if x.startswith("+"))
                         if set(fs) & set(groups[w.name])}
            moved = [f"{p} (proved in run {elsewhere['-' + p]})" for p in left_out
                     if f"-{p}" in elsewhere]
            left_out = [p for p in left_out if f"-{p}" not in elsewhere]
            if moved:
                print(f"prove:   proved in a run of its own: {' '.join(moved)}")
            if left_out:
                print(f"prove:   left out, not proved (docs/PROOF.md): {' '.join(left_out)}")
            for g in w.failed:
                print(f"prove:   not proved: {g}")
            for g in w.smoke_failed:
                print(f"prove:   smoke test failed (a precondition that cannot hold, or code "
                      f"the proof finds dead): {g}")
            for g in w.wrong_model[:5]:
                print(f"prove:   goal of another memory model than {model}: {g}")
            if w.error:
                print(f"prove:   error: {w.error}")
            ok = ok and not w.error and w.proved == w.total and w.total > 0 and \
                not w.smoke_failed and not w.wrong_model
        if wps:
            print("prove: wp total by prover: "
                  + ", ".join(f"{k} {v}" for k, v in sorted(totals.items())))
        for fut in selftests:
            p, caught, what = fut.result()
            print(f"prove: self-test {p.name} ({p.check}): "
                  f"{'caught' if caught else 'NOT CAUGHT'}: {what}")
            ok = ok and caught
    print(f"prove: {'ok' if ok else 'FAILED'} in {time.monotonic() - t0:.0f} s "
          f"(logs in {BUILD.relative_to(ROOT)}/)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
