"""WP runs: the ACSL contracts of firmware/core, per group of functions of prove/wp_groups.txt,
proved by Qed (WP's own simplifier) and the SMT solvers through Why3; and the lemmas of the
proof's logic, proved in a run of their own."""

from __future__ import annotations

import dataclasses
import re
import time
from pathlib import Path

from . import parsed, task_idle
from .frama import (
    BUILD,
    CORE,
    PROVE,
    ROOT,
    core_sources,
    cpp_args,
    cpu_time,
    frama_c,
    frama_c_until,
)

PROVERS = "z3,cvc4"
# The first pass of every run asks CVC4 alone: both solvers on a goal cost both cores until one
# of them proves it, and a smoke test both of them its whole second. CVC4 alone proves every
# goal of every run but two (estop_ct_equal's equal_bit and the lemma eq_bit: bit 8 of a byte
# minus one). Measured on an idle 2-core machine (issue 24), both solvers against CVC4 alone:
# loops 96 s against 38 s, auth 115 s against 67 s; datagram 168 s, entry 33 s, init 31 s,
# link 7 s alone. A goal CVC4 leaves goes to the retry below, with both solvers, and with it
# its function's smoke tests: each function's smoke tests are asked of every solver that
# proved one of its goals. The plants and the mutants try the same two passes (selftest.py).
FIRST_PASS_PROVERS = "cvc4"
# A whole WP run's bound (a hung frama-c fails the run, not CI's 90 minutes). make test runs
# make prove at low priority beside the busiest steps: the datagram run took 533 s there (the
# fresh-machine run of 09bd4ca, 176 s idle), and the steps run under Typed reached 600 s.
WP_TIMEOUT_S = 1500
# Typed: WP's memory model in which the contracts are satisfiable for real inputs; its
# hypotheses are checked at every call and every run has smoke tests (MODEL_CHECKS). Since
# issue 24's thirty-seventh round every run is under it, and wp_groups refuses a run under a
# model without those checks: under Caveat the pointers a function receives were assumed
# separated and valid, unchecked (some of those hypotheses were false), and some contracts
# were vacuous (docs/PROOF.md "Known holes").
# A slot's fill is bounded by a quantified invariant (slots_ok): Qed instantiates it for the 8
# slots. The timeout leaves the slowest goal (about 16 s on an idle 2-core machine) room on a
# loaded one; a run on a machine busy with other work timed out at 20 s.
WP_MODEL = "Typed"
# A run under Typed also checks the hypotheses of its model at every call and runs smoke tests
# (a precondition that cannot hold or code the proof finds dead fails the run).
# A smoke test passes when neither solver proves \false at its point in the time it gets, so
# each one that passes costs that time of both: 1 s (WP's default is 2 s) halves the cost of
# the Typed runs' 137 smoke tests (about 140 s of make prove's 2 workers). Still able to fail:
# the self-test's dead-branch plant is caught at 1 s. In a run bounded by CPU time (run_wp's
# cpu_limited) CVC4 gets SMOKE_RLIMIT resource units instead of that second of wall time, and
# WP's wall limit is SMOKE_WALL_GUARD_S, against a hang (Why3 stops a call at about twice its
# limit: a starved CVC4 ran out of its second, and the smoke test passed, where an idle one
# could have proved \false). 20,000 units are about 1 s of CPU on the slower 2-core machine
# of issue 24's thirteenth round; the dead-branch plant is caught at 1,000. Z3 gets
# SMOKE_Z3_RLIMIT of its own units (rlimit=) since the fourteenth: about 0.7 s of CPU here on a
# problem it cannot finish; the dead-branch plant is caught by Z3 alone
# (tools/proof/solvers/cpu-limited).
# 50,000 since issue 24's thirty-eighth round, the first in which make prove's smoke tests
# reached a solver at all: the plant dead-branch-past-qed (a branch the loop's invariant rules
# out, which Qed does not see) is caught by CVC4 at 30,000 units and not at 25,000 or 20,000,
# nor by Z3 at 1,000,000 or 5,000,000. Measured there on the idle machine: 20,000 units were
# about 0.08 s of CPU a smoke test, not the 1 s above; the auth run (97 smoke tests) 34 CPU-s
# at 20,000, 48 at 50,000, 74 at 100,000.
SMOKE_TIMEOUT_S = 1
SMOKE_RLIMIT = 50000
SMOKE_Z3_RLIMIT = 1000000
# Z3 overruns its units in some phase on one smoke test of ct (it gives up in 0.05 s at 200,000
# units, and ran over 30 s at 1,000,000): the CPU time that ends such a call, 4 times what its
# units cost here, so a verdict within them is the same on a machine up to 4 times slower
# (issue 24's forty-first round; the wall guard ended it before, after 10 s in each of the 3 ct
# runs).
SMOKE_Z3_CPU_S = 3
SMOKE_WALL_GUARD_S = 10
MODEL_CHECKS = {"Typed": ["-wp-check-memory-model", "-wp-smoke-tests"]}
MODEL_TAGS = {"Typed": "typed_", "Caveat": "typed_caveat_"}  # how WP names their goals
# -wp-no-ground: Qed without its aggressive ground simplifications. frama-c's own work (WP's
# calculus, Qed, Why3's tasks; the solver answering at once) took 42 CPU-s against 61 in the
# tcp run and 46 against 64 in datagram, Qed proving the same goals; with the solvers, tcp 118
# CPU-s against 148 and datagram 89 against 115, every goal proved (paired runs, issue 24's
# forty-fourth round). Tried there and not kept: -wp-no-core (72 and 79), -wp-no-filter-init (71
# and 74), -wp-no-extensional (60 and 63). The clock run keeps them (%ground): 223 CPU-s with
# them against 280 without, side by side, its goals harder without (clock_link 31 s against 16).
# -wp-par 1 since issue 24's forty-sixth round: make prove runs two analyses at once (--jobs)
# beside make test's other steps, so two solvers a run made four on two cores; alone on the
# idle machine the tcp run took 97 CPU-s with one against 116 with two (the forty-fifth).
# With one call at a time a run waited up to 50 ms for each verdict (Frama-C's command line
# polls its running calls in Task.on_idle, then sleeps 50 ms): alone, a fifth to a third of a
# run's wall time. Every run loads a module that polls every 2 ms (TASK_IDLE: task_idle.ml),
# built once (task_idle.py: frama-c -load-script built it beside the script at every run, and
# two runs starting together raced on it). make prove alone: 764 s for 1,471 CPU-s with it
# (both cores busy 96 % of the time), 822 s for 1,309 without (80 %). In make test, fresh
# clones in turn left about 35 CPU-s less of the cores idle (issue 24's forty-eighth round).
WP_OPTS = ["-wp-par", "1", "-wp-bound-forall-unfolding", "8", "-wp-no-ground"]
# The time a goal gets is the CPU time its solver uses, not the wall time it waits: make test
# runs make prove at low priority beside other work, where a goal is starved. Bounded by wall
# time, a goal of 6 s on an idle machine took more than 40 s there (CI runs of 6d63619 and
# 9e6601f), and on a slower machine (a fresh-machine run of 7ff5bff, 1.6 times the CPU time)
# take_valid's valid_inv_3 (46 s of CPU idle) failed both passes, 90 s and 150 s of wall time:
# a verdict that the load decided. tools/proof/solvers/cpu-limited bounds each solver by
# ESTOP_SOLVER_CPU_S; WP and Why3 bound the wall time WALL_GUARD times longer, against a hang.
# A goal proved costs its own time whatever the limit, so a longer one costs a passing run
# nothing; a goal a solver cannot prove costs all of it (the two that CVC4 cannot are asked of
# both solvers at once: the runs lemmas and ct, %both).
GOAL_TIMEOUT_S = 90
# A run that leaves goals unproved at GOAL_TIMEOUT_S is run once more with this per-goal
# limit and both solvers; the output says so. Still a proof: only the time the solvers get
# changes. 300 s since the seventeenth round (150 before): on a machine twice as slow, under
# make test's load, clock_brake_due (888,038 of CVC4's units; 64 s alone idle there) ran out
# 90 s of CPU, then 150 s in the retry: the CPU time per unit more than doubled under load.
GOAL_RETRY_TIMEOUT_S = 300
# The retry asks CVC4 each goal in this many orders of its problem's assertions, its own with
# half of GOAL_RETRY_TIMEOUT_S, the others the rest (tools/proof/solvers/cpu-limited): the
# first pass and the retry had both asked the one order WP wrote, and a goal whose search
# hangs on it failed both (tcp's leaves_stopped_only_by_release in the CI run of fcfba03;
# issue 24's forty-third round). Any order is the same logic: a proof in one is a proof.
RETRY_ORDERS = 4
WALL_GUARD = 10
# OCaml's collector for WP's frama-c: a larger minor heap (16M words) and a major heap let grow
# to 5 times its live data before the collector works harder (o=400, 120 by default). WP's
# simplifier Qed allocates about 10^10 words in the datagram run; with this setting frama-c
# alone (-wp-prover qed) took 75 CPU-s there against 88, and 67 against 77 in tcp, paired runs
# on the idle machine (issue 24's thirty-ninth round; steps, clock, udp and entry within 2 s
# of before). Eva gained nothing (98 CPU-s either way) and keeps the default.
WP_OCAMLRUNPARAM = "s=16M,o=400"
WP_CACHE = BUILD / "wp-cache"
# Frama-C's wait for its solvers, polled every 2 ms instead of 50 (task_idle.ml says why).
TASK_IDLE = task_idle.SOURCE
# Per-run WP options of prove/wp_groups.txt ("%name").
WP_FLAGS = {
    "split": ["-wp-split"],  # conjunctions and branches as sub-goals (mostly Qed's then)
    "both": [],  # the first pass asks both solvers (first_pass_provers)
    # Qed keeps the branches it would prune: the udp and auth runs take half the CPU time with
    # it; datagram, entry and init took longer, tcp had not ended after 12 minutes (124 s
    # without), datagram failed 8 goals (prove/wp_groups.txt).
    "noprune": ["-wp-no-pruning"],
    # The terms WP names with a let written out in place: in the tcpframe run a quantified
    # clause over the slots' fills, its terms let-bound, was never instantiated toward its
    # goal, which CVC4 and Z3 then ran out of their time on (issue 24's thirty-sixth round).
    "nolet": ["-wp-no-let"],
    # Qed's aggressive ground simplifications, which WP_OPTS turns off for the other runs
    "ground": ["-wp-ground"],
}
LEMMAS = "lemmas"  # the run that proves the lemmas of prove/*.h (-wp-fct runs skip them)


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
    smoke_unanswered: int = 0  # passed smoke tests no solver answered (it never ran)
    wrong_model: list[str] = dataclasses.field(default_factory=list)
    wall_s: float = 0.0
    cpu_s: float = 0.0  # frama-c's and its solvers' (frama.cpu_time)


def wp_groups(path: Path = PROVE / "wp_groups.txt") -> list[tuple[str, list[str]]]:
    """name: functions [%flag] [@Model]. A run proves every clause of its functions: an entry
    that would leave a property out of a run (-prop) or restrict it to one (+prop) is refused,
    and so is a run under a model whose hypotheses are not checked (Caveat)."""
    groups = []
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            name, fcts = line.split(":", 1)
            bad = [f for f in fcts.split() if f.startswith(("-", "+"))]
            if bad:
                raise SystemExit(f"prove: error: {path.name}: run {name.strip()} filters "
                                 f"properties ({' '.join(bad)}); every clause is proved where "
                                 "it is written")
            model = model_of(fcts.split())
            if model not in MODEL_CHECKS:
                raise SystemExit(f"prove: error: {path.name}: run {name.strip()} is under "
                                 f"{model}, whose hypotheses WP does not check and which has no "
                                 "smoke tests; every run is under Typed")
            groups.append((name.strip(), fcts.split()))
    return groups


def first_pass_provers(fcts: list[str]) -> str:
    """CVC4 alone, or both solvers for a run marked %both (the goals of bit 8 of a byte minus
    one, which CVC4 cannot prove: the runs lemmas and ct)."""
    return PROVERS if "%both" in fcts else FIRST_PASS_PROVERS


def run_flags(fcts: list[str]) -> list[str]:
    """A run's options (%flag, @Model) among its functions' names, in their order."""
    return [f for f in fcts if f.startswith(("@", "%"))]


def model_of(fcts: list[str]) -> str:
    return next((f[1:] for f in fcts if f.startswith("@")), WP_MODEL)


def model_checks(model: str, cpu_limited: bool) -> list[str]:
    """The checks a run under this model asks for: its hypotheses and smoke tests (Typed),
    with WP's wall limit on a smoke test: SMOKE_TIMEOUT_S, or only SMOKE_WALL_GUARD_S against
    a hang where the solvers' own units bound it (cpu_limited)."""
    if model not in MODEL_CHECKS:
        return []
    smoke_s = SMOKE_WALL_GUARD_S if cpu_limited else SMOKE_TIMEOUT_S
    return [*MODEL_CHECKS[model], "-wp-smoke-timeout", str(smoke_s)]


def parse_args(core_dir: Path) -> list[str]:
    """What a WP run parses: the core's sources with the contracts (parsed.py saves this parse
    of firmware/core once for all of make prove's runs over it)."""
    return [*cpp_args(core_dir, f"-include {PROVE / 'contracts.h'}"),
            *map(str, core_sources(core_dir)), "-inline-calls", inline_list()]


def inline_list() -> str:
    names = []
    for raw in (PROVE / "wp_inline.txt").read_text().splitlines():
        names += raw.split("#", 1)[0].split()
    return ",".join(names)


# A goal WP names without a solver's verdict and not as proved ("trivial" is a goal Qed proved:
# WP prints it so when it has no solver to report beside it).
GOAL_NOT_VALID = r"^\[wp\] Goal (\S+) : (?!Valid|trivial)"
# A goal one solver alone left (a Caveat run's first pass asks CVC4 alone): WP names the
# solver in the brackets and its verdict after the goal, "[wp] [CVC4 1.8] Goal g : Timeout".
# Missed until the fresh-machine run of ddecf41, where such a goal failed the run instead of
# going to the retry (clock_brake_due, 90 s under load, 26 s idle).
SOLVER_NOT_VALID = r"^\[wp\] \[[^\]]+\] Goal (\S+) : (?!Valid)"
# The verdict that opens a line of a goal several solvers left, "[wp] [Timeout] Goal g".
VERDICT_NOT_VALID = r"^\[wp\] \[(?:Timeout|Unknown|Failed|Stepout)[^\]]*\] "
# WP's name of a smoke test's goal has this in it (its function's name before).
SMOKE_TAG = "_wp_smoke_"
# A goal or smoke test that failed, as WP prints it: enough to catch a mutant.
FIRST_FAILURE = re.compile(VERDICT_NOT_VALID + r"(?:Goal|Smoke-test) (\S+)|" + GOAL_NOT_VALID
                           + "|" + SOLVER_NOT_VALID, re.M)
# A solver WP cannot find: no goal of the run means anything (a mutant's run stopped at its
# first goal would have counted as caught).
MISSING_SOLVER = re.compile(r"^\[wp\] User Error: (Prover '[^']+' not found[^\n]*)", re.M)


def refuse_missing_solver(out: str) -> None:
    """Stops make prove when a WP run's log says a solver is missing."""
    m = MISSING_SOLVER.search(out)
    if m:
        raise SystemExit(f"prove: error: {m.group(1)} (install it: scripts/ensure-debs prove)")


def failed_goals(out: str) -> list[str]:
    """The goals a run's log names as not proved, in either of WP's forms (several solvers, or
    one), each once."""
    failed: list[str] = []
    for pattern in (VERDICT_NOT_VALID + r"Goal (\S+)", GOAL_NOT_VALID, SOLVER_NOT_VALID):
        for m in re.finditer(pattern, out, re.M):
            if m.group(1) not in failed:  # WP may print a goal's verdict twice
                failed.append(m.group(1))
    return failed


def run_wp(name: str, core_dir: Path, fcts: list[str], env: dict[str, str],
           goal_timeout_s: int = GOAL_TIMEOUT_S, cache: bool = False,
           only_prop: str = "", first_failure: bool = False,
           provers: str = PROVERS, log_name: str = "", cpu_limited: bool = True,
           orders: int = 1) -> WpResult:
    """One WP run. goal_timeout_s is the CPU time a solver gets on a goal (cpu_limited), or
    the wall time (not cpu_limited: the self-test's planted goals, false at any limit, whose
    solvers run their limit out). A smoke test gets SMOKE_RLIMIT of CVC4's resource units and
    SMOKE_Z3_RLIMIT of Z3's (cpu_limited), or SMOKE_TIMEOUT_S of wall time. only_prop
    restricts it to one property: the self-test's planted faults only (the planted goal costs
    its timeout), never a run of make prove's proof. first_failure stops it at the first goal
    that fails (the self-test's mutants). orders: CVC4's goals each in that many orders of
    their assertions (the retry). The cache is kept by name; the log is
    wp-<log_name or name>.log."""
    t0 = time.monotonic()
    log = BUILD / f"wp-{log_name or name}.log"
    names = [f for f in fcts if not f.startswith(("@", "%"))]
    flags = [opt for f in fcts if f.startswith("%") for opt in WP_FLAGS[f[1:]]]
    model = model_of(fcts)
    target = ["-wp-prop=@lemma"] if name == LEMMAS else ["-wp-fct", ",".join(names)]
    args = ["-load-module", str(task_idle.module(TASK_IDLE, BUILD)),
            *parsed.head(core_dir, parse_args(core_dir)), "-wp", *target,
            # One model a run: a second -wp-model is added to the first, not put in its place
            # (Typed and Caveat together named the goals typed_caveat_*).
            "-wp-model", model, "-wp-prover", provers, *WP_OPTS, *model_checks(model, cpu_limited),
            "-wp-timeout", str(goal_timeout_s * (WALL_GUARD if cpu_limited else 1)), *flags]
    env = dict(env, OCAMLRUNPARAM=WP_OCAMLRUNPARAM)
    if cpu_limited:
        env = dict(env, ESTOP_SOLVER_CPU_S=str(goal_timeout_s), ESTOP_SMOKE_RLIMIT=str(
            SMOKE_RLIMIT), ESTOP_SMOKE_Z3_RLIMIT=str(SMOKE_Z3_RLIMIT),
            ESTOP_SMOKE_Z3_CPU_S=str(SMOKE_Z3_CPU_S), ESTOP_SOLVER_ORDERS=str(orders))
    if cache:
        # The solvers' verdicts by goal (a hash of the goal and the prover): a run again with
        # a longer timeout re-tries only what timed out. Emptied by every make prove.
        args += ["-wp-cache", "update", "-wp-cache-dir", str(WP_CACHE / name)]
    if only_prop:
        args.append("-wp-prop=" + only_prop)
    res = WpResult(name, 0, 0, {}, [], log)
    if first_failure:
        rc, out, stopped = frama_c_until(args, log, WP_TIMEOUT_S, env, FIRST_FAILURE)
        refuse_missing_solver(out)
        res.wall_s = time.monotonic() - t0
        res.cpu_s = cpu_time(log)
        if stopped:
            m = FIRST_FAILURE.search(out)
            res.failed.append(next((g for g in m.groups() if g), "?") if m else "?")
            return res
    else:
        rc, out = frama_c(args, log, WP_TIMEOUT_S, env)
        refuse_missing_solver(out)
        res.wall_s = time.monotonic() - t0
        res.cpu_s = cpu_time(log)
    m = re.search(r"Proved goals:\s+(\d+)\s*/\s*(\d+)", out)
    if rc != 0 or m is None:
        res.error = f"frama-c failed (exit {rc}); see {log.relative_to(ROOT)}"
        tail = [x for x in out.splitlines() if "Error" in x or "error" in x][:5]
        if tail:
            res.error += ": " + " | ".join(tail)
        return res
    res.proved, res.total = int(m.group(1)), int(m.group(2))
    res.by_prover = prover_counts(out)
    res.failed += failed_goals(out)
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
    res.smoke_unanswered = smoke_unanswered(out, len(smoke) - len(res.smoke_failed))
    # Every goal carries the run's model and no other one (WP names them typed_* under Typed,
    # typed_caveat_* under Caveat: Typed with Caveat's hypotheses, which a run under Typed
    # alone must not get).
    tag = MODEL_TAGS[model]
    goals = set(re.findall(r"Goal (\w+)", out)) | set(smoke)
    res.wrong_model = sorted(g for g in goals if not g.startswith(tag) or any(
        g.startswith(tag + extra) for extra in ("caveat_", "ref_", "raw_")
        if extra not in tag))


# A solver's verdict on a proof goal, and a line of WP's count by prover after "Proved goals".
SOLVER_VALID = re.compile(r"^\[wp\] \[((?:CVC4|Z3|Alt-Ergo)[^\]]*)\] Goal (\S+) : Valid", re.M)
PROVER_COUNT = re.compile(
    r"^\s+(Qed|Z3[^:]*|CVC4[^:]*|Alt-Ergo[^:]*|Terminating|Unreachable):\s+(\d+)", re.M)
NOT_SOLVERS = ("Qed", "Terminating", "Unreachable")


def prover_counts(out: str) -> dict[str, int]:
    """WP's count by prover after "Proved goals" (a solver's name without its version), or
    none where the log has no count."""
    m = re.search(r"Proved goals:\s+\d+\s*/\s*\d+", out)
    counts: dict[str, int] = {}
    for pm in PROVER_COUNT.finditer(out[m.end():] if m else ""):
        prover = pm.group(1).split()[0]
        counts[prover] = counts.get(prover, 0) + int(pm.group(2))
    return counts


def smoke_unanswered(out: str, passed: int) -> int:
    """How many of a run's passed smoke tests no solver answered. A smoke test passes when no
    solver proves \\false, so one whose solver never ran passes too: until issue 24's
    thirty-eighth round every smoke test of make prove's runs did (tools/proof/solvers/
    cpu-limited exited before the solver, under Why3's own CPU limit), and no check saw it.
    WP's count by solver after "Proved goals" holds the proof goals each solver proved and the
    smoke tests it answered; a solver that did not run answered none."""
    answers = sum(n for p, n in prover_counts(out).items() if p not in NOT_SOLVERS)
    proved_by_solver = len(set(SOLVER_VALID.findall(out)))
    return max(0, passed - max(0, answers - proved_by_solver))


def goal_function(goal: str, model: str, fcts: list[str]) -> str | None:
    """The function of fcts whose goal this is (WP names a goal <model tag><function>_<kind>_
    ...; a goal of an inlined callee is its caller's), or None (a lemma's, or not known)."""
    rest = goal.removeprefix(MODEL_TAGS[model])
    names = sorted((f for f in fcts if not f.startswith(("@", "%"))), key=len, reverse=True)
    return next((f for f in names if rest.startswith(f + "_")), None)


def retry_fcts(name: str, fcts: list[str], failed: list[str]) -> list[str]:
    """What the retry runs: the functions of the goals the first pass left, with the group's
    options, or the whole group where one of them belongs to no function (the lemmas)."""
    model = model_of(fcts)
    owners = [goal_function(g, model, fcts) for g in failed]
    if name == LEMMAS or None in owners:
        return fcts
    return run_flags(fcts) + sorted({o for o in owners if o})


def merge_retry(first: WpResult, retry: WpResult) -> WpResult:
    """The first pass's result with a retry over some or all of its functions: the goals those
    functions have are counted by the retry (WP's own count, not the failures parsed), the
    others by the first pass, which proved them all; the smoke tests of the first pass, and
    the retry's failed ones."""
    left = retry.total - retry.proved
    by_prover = dict(first.by_prover)  # and the solver of each goal the retry proved
    out = retry.log.read_text() if retry.log.exists() else ""
    for g in first.failed:
        m = re.search(r"^\[wp\] \[(\S+)[^\]]*\] Goal " + re.escape(g) + " : Valid", out, re.M)
        if m:
            by_prover[m.group(1)] = by_prover.get(m.group(1), 0) + 1
    return dataclasses.replace(
        first, proved=first.total - left if retry.total else 0, by_prover=by_prover,
        failed=retry.failed, error=retry.error,
        smoke_failed=sorted(set(first.smoke_failed) | set(retry.smoke_failed)),
        smoke_unanswered=first.smoke_unanswered + retry.smoke_unanswered,
        wrong_model=sorted(set(first.wrong_model) | set(retry.wrong_model)),
        wall_s=first.wall_s + retry.wall_s, cpu_s=first.cpu_s + retry.cpu_s)


def run_wp_retrying(name: str, fcts: list[str], env: dict[str, str]) -> tuple[list[str], WpResult]:
    """A run of the core's group with CVC4 alone, and once more, with both solvers and
    GOAL_RETRY_TIMEOUT_S a goal (CVC4 in RETRY_ORDERS orders of each), over the functions of
    the goals it left unproved (the cache keeps what the first pass proved; the retry asks Z3
    those functions' smoke tests too); the goals the first pass left unproved, and the whole
    result."""
    (WP_CACHE / name).mkdir(parents=True, exist_ok=True)
    first = run_wp(name, CORE, fcts, env, GOAL_TIMEOUT_S, cache=True,
                   provers=first_pass_provers(fcts))
    if not first.failed or first.error:
        return [], first
    again = retry_fcts(name, fcts, first.failed)
    if first.proved + len(first.failed) + len(first.smoke_failed) != first.total:
        again = fcts  # a goal left that the log does not name: its function is not known
    retry = run_wp(name, CORE, again, env, GOAL_RETRY_TIMEOUT_S, cache=True,
                   log_name=f"{name}-retry", orders=RETRY_ORDERS)
    return first.failed, merge_retry(first, retry)


def proof_goals(w: WpResult) -> tuple[int, int]:
    """(proved, total) of a run's proof goals. WP's "Proved goals" counts its smoke tests
    among them, a passed one as proved (the `steps` run: 264/264 are 201 proof goals and 63
    smoke tests); until issue 24's sixteenth round make prove printed that sum as its goals."""
    passed_smoke = w.smoke - len(w.smoke_failed)
    return max(0, w.proved - passed_smoke), max(0, w.total - w.smoke)


def ok(w: WpResult) -> bool:
    return not w.error and w.proved == w.total and w.total > 0 and not w.smoke_failed \
        and not w.smoke_unanswered and not w.wrong_model
