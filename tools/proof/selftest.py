"""The self-test of `make prove`: the same analyses on copies of the core with faults in them.

Named plants (prove/planted.txt): each must make its analysis report the expected alarm, rule
or goal. Plants with the same check share one copy and one run (each is still judged by its own
expected failure), so the self-test costs one Eva run and one WP run per group it tries.

Mutants (prove/mutants_scope.txt): tools/mutants.py's mutants of the lines that decide a state
change. Each is tried by the WP run of its function (or, for a helper WP inlines, of the
functions that call it); one that every goal and smoke test still passes must be listed in
prove/mutants_equivalent.txt with the reason the proofs cannot see it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

from . import eva, wp
from .frama import BUILD, CORE, PROVE, core_functions

# A mutant's goals get 40 s, less than make prove's own (90 s, then 150 s): a caught mutant
# usually fails by running out of time, and at 90 s the two of make prove added 50 s to its
# tail (CI run of 017436c). So "caught" means a goal the solvers did not prove in 40 s of CPU
# time each (wp.run_wp: bounded by wall time, a solver starved beside make test's other steps
# could count a mutant caught that an idle one proves).
GOAL_TIMEOUT_S = 40
# Less for the runs whose every goal proves in a fraction of it: make prove's sample comes from
# `entry`, whose slowest goal took 4.2 s beside make test's other steps (CVC4; the CI run of
# d919dff). A caught mutant runs its false goal's limit out in both solvers, so 12 s instead of
# 40 cut each of the two by about 55 CPU-s of both solvers (57 s and 35 s of wall time alone
# on the idle machine, against about 85 and 62; issue 24's thirtieth round). Still a check that
# can fail: make prove fails when a goal of the unmutated run took longer than this limit
# (mutant_limit_errors), so a goal a mutant leaves unproved at it is one the code proves.
MUTANT_TIMEOUT_S = {"entry": 12}


def mutant_timeout_s(check: str) -> int:
    """The CPU time a mutant's goal gets in the run of check (wp:RUN[:FUNCTION])."""
    return MUTANT_TIMEOUT_S.get(check.split(":")[1], GOAL_TIMEOUT_S)


def slowest_goal_s(log: str) -> float:
    """The longest time a proved goal of a WP log took: its solver's, or Qed's where Qed alone
    proved it (stricter than the solvers' alone)."""
    times = [0.0]
    for m in re.finditer(r"Goal \w+ : Valid (?:\(Qed:[^)]*\) )?\((\d+(?:\.\d+)?)(ms|s)\)",
                         log):
        t = float(m.group(1))
        times.append(t / 1000 if m.group(2) == "ms" else t)
    return max(times)


def mutant_limit_errors(runs: dict[str, tuple[list[str], wp.WpResult]]) -> list[str]:
    """The runs of MUTANT_TIMEOUT_S among this make prove's WP runs (name: the goals its first
    pass left to the retry, and its result) that have a goal slower than their mutants' limit:
    there a mutant's unproved goal would not show that the mutant broke the proof. A goal left
    to the retry ran out wp.GOAL_TIMEOUT_S in the first pass, more than any mutant's limit; the
    first pass's log has the times of the others."""
    errors = []
    for run, limit in sorted(MUTANT_TIMEOUT_S.items()):
        if run not in runs:
            continue
        retried, w = runs[run]
        if retried:
            errors.append(f"{run}'s goals {' '.join(retried)} needed the retry, more than its "
                          f"mutants' {limit} s (selftest.MUTANT_TIMEOUT_S)")
        elif w.log.exists():
            slowest = slowest_goal_s(w.log.read_text())
            if slowest > limit:
                errors.append(f"{run}'s slowest goal took {slowest:.1f} s, more than its "
                              f"mutants' {limit} s (selftest.MUTANT_TIMEOUT_S)")
    return errors
# A planted goal is false: it fails at any timeout, and costs this one of both solvers. At 20 s
# the plants' nine false goals took about 360 s of the two workers (the CI run of efe87a5). Wall
# time (wp.run_wp's cpu_limited): a false goal fails at any limit, and a starved solver costs
# the other steps less. 4 s since issue 24's thirtieth round (10 before): each planted goal ran
# its whole limit out in both solvers (a plant's goals at 30 s took 30 s each), so the plants
# alone took 183 s and 361 CPU-s of the idle machine at 10 s, 119 s and 234 CPU-s at 4 s, and
# all 22 were caught at both. 2 s since the thirty-second: 117 s and 229 CPU-s at 4 s, 89 s
# and 172 CPU-s at 2 s, all 23 caught at 4, 2 and 1 s. The limit is no evidence: the plant's
# fault (prove/planted.txt) makes its goal false, and make prove's own run proves the same goal
# of the unplanted code. 1 s since the forty-seventh: the whole self-test alone on the idle
# machine 287 CPU-s against 343 at 2 s, every plant caught (as at 1 s in the thirty-second).
PLANT_TIMEOUT_S = 1


@dataclasses.dataclass
class Plant:
    name: str
    file: str        # in firmware/core
    old: str         # text replaced (must occur exactly once)
    new: str
    check: str       # "eva" or "wp:<group>[:<function>]"
    expect: str      # an alarm, a rule, or a goal (its name or a part of it) that must fail;
                     # eva: "a|b", either
    prop: str = ""   # wp: only this property is tried (the planted goal costs its timeout)
    copy: str = ""   # plants of one check and one copy are planted and tried together
    calls: str = ""  # eva: the driver's calls (its loop's case numbers) the copy needs; all
                     # when empty. A copy makes the calls of all its plants.
    chunks: str = ""  # eva: "whole" when the fault needs TCP chunks of whole frames only; a
                      # copy tries every length unless all its plants say so


def plants(path: Path = PROVE / "planted.txt") -> list[Plant]:
    out = []
    for block in path.read_text().split("\n---\n"):
        fields: dict[str, str] = {}
        key = None
        for raw in block.splitlines():
            if raw.startswith("#"):
                continue
            m = re.match(r"^(name|file|check|expect|prop|copy|calls|chunks|old|new):\s?(.*)$", raw)
            if m:
                key = m.group(1)
                fields[key] = m.group(2)
            elif key in ("old", "new"):
                fields[key] += "\n" + raw
        if fields:
            out.append(Plant(fields["name"], fields["file"], fields["old"], fields["new"],
                             fields["check"], fields["expect"], fields.get("prop", ""),
                             fields.get("copy", ""), fields.get("calls", ""),
                             fields.get("chunks", "")))
    return out


def driver_calls(group: list[Plant]) -> int:
    """The calls of the Eva driver that a copy makes, one bit per case: every plant's, all of
    them when one plant names none. Fewer calls reach fewer states, so a fault Eva finds with
    them is there with all (and a plant that no call reaches is not caught: make prove fails)."""
    mask = 0
    for p in group:
        if not p.calls.split():
            return eva.ALL_CALLS
        for c in p.calls.split():
            if not 0 <= int(c) < eva.ALL_CALLS.bit_length():
                raise SystemExit(f"prove: error: self-test {p.name}: no driver call {c}")
            mask |= 1 << int(c)
    return mask


def whole_chunks(group: list[Plant]) -> bool:
    """A copy's TCP chunks are whole frames only when every plant of it says so (chunks:
    whole): fewer lengths reach fewer states, as fewer calls do."""
    for p in group:
        if p.chunks not in ("", "whole"):
            raise SystemExit(f"prove: error: self-test {p.name}: chunks: {p.chunks} "
                             "(want whole, or no such line)")
    return all(p.chunks == "whole" for p in group)


def planted_copy(name: str, edits: list[tuple[str, str, str]]) -> Path:
    """A copy of the core with each (file, old, new) edit made; old must occur once."""
    dst = BUILD / f"planted-{name}"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(CORE, dst)
    for file, old, new in edits:
        target = dst / file
        src = target.read_text()
        if src.count(old) != 1:
            raise SystemExit(f"prove: error: self-test {name}: a planted site occurs "
                             f"{src.count(old)} times in {file} (want 1)")
        target.write_text(src.replace(old, new))
    return dst


def wp_fcts(check: str) -> list[str]:
    parts = check.split(":")  # wp:GROUP or wp:GROUP:FUNCTION
    fcts = dict(wp.wp_groups())[parts[1]]
    if len(parts) > 2:  # the group's options on one of its functions
        fcts = wp.run_flags(fcts) + [parts[2]]
    return fcts


def run_plants(check: str, group: list[Plant], env: dict[str, str]
               ) -> list[tuple[Plant, bool, str]]:
    """The plants of one check and copy, planted together and tried in one run: each caught
    when the run reports its own expected failure."""
    tag = re.sub(r"\W", "-", check) + (f"-{group[0].copy}" if group[0].copy else "")
    core_dir = planted_copy(tag, [(p.file, p.old, p.new) for p in group])
    out = []
    if check == "eva":
        r = eva.run_eva(f"planted-{tag}", core_dir, 0, env, driver_calls(group),
                        whole_chunks(group))
        helpers = core_functions(core_dir)
        found = [eva.copies_unnumbered(a, helpers)
                 for a in r.alarms + r.invalid + r.rules_not_shown]
        for p in group:
            hits = [a for a in found if any(e in a for e in p.expect.split("|"))]
            out.append((p, bool(hits), hits[0] if hits else
                        f"{len(r.alarms)} alarms, none '{p.expect}'"
                        + (f" ({r.error})" if r.error else "")))
        return out
    props = ",".join(p.prop for p in group if p.prop)
    # A planted goal must fail both solvers (make prove's retry asks both); a planted dead
    # branch must fail a smoke test of CVC4 alone (make prove's first pass asks it alone).
    fcts = wp_fcts(check)
    smoke = any(wp.SMOKE_TAG in p.expect for p in group)
    # A planted dead branch runs under make prove's own limits (the goals' CPU time): its
    # smoke test meets the solvers as make prove's runs do. Until issue 24's thirty-eighth
    # round the plants ran without them, and caught what make prove's own smoke tests could
    # not (each of those ended before its solver started, and passed).
    w = wp.run_wp(f"planted-{tag}", core_dir, fcts, env,
                  wp.GOAL_TIMEOUT_S if smoke else PLANT_TIMEOUT_S, only_prop=props,
                  provers=wp.first_pass_provers(fcts) if smoke else wp.PROVERS,
                  cpu_limited=smoke)
    for p in group:
        hit = any(p.expect in g for g in w.failed + w.smoke_failed)
        out.append((p, hit and not w.error, (f"{p.expect} not proved" if hit else
                    f"{w.proved}/{w.total} proved, {p.expect} not among the failures")
                    + (f" ({w.error})" if w.error else "")))
    return out


def plant_checks() -> dict[tuple[str, str], list[Plant]]:
    """The plants by (check, copy): one planted copy and one run each. A plant that would
    mask another (a read made invalid cuts Eva's states where a later fault needs them) gets
    a copy of its own."""
    by_check: dict[tuple[str, str], list[Plant]] = {}
    for p in plants():
        by_check.setdefault((p.check, p.copy), []).append(p)
    return by_check


# ---- mutants ---------------------------------------------------------------------------------

@dataclasses.dataclass
class MutantTry:
    key: str
    check: str
    caught: bool
    what: str
    # False: not a mutant (it does not compile, or Frama-C refuses it): nothing was tried, so
    # it counts neither as caught nor as surviving (until issue 24's twenty-sixth round it
    # counted as caught, and a sample of such could pass the self-test having tried nothing).
    tried: bool = True


def scope(path: Path = PROVE / "mutants_scope.txt") -> dict[str, str]:
    """function -> the check that tries its mutants ("wp:<group>:<function>")."""
    groups = wp.wp_groups()
    where = {f: g for g, fs in groups for f in fs if not f.startswith(("@", "%"))}
    out: dict[str, str] = {}
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fn, _, via = (x.strip() for x in line.partition("via"))
        target = via or fn
        if target not in where:
            raise SystemExit(f"prove: error: mutants_scope.txt: {target} is in no WP run")
        out[fn] = f"wp:{where[target]}:{target}"
    return out


def equivalents(path: Path = PROVE / "mutants_equivalent.txt") -> dict[str, str]:
    out = {}
    for raw in path.read_text().splitlines():
        if raw.strip() and not raw.startswith("#"):
            key, _, why = raw.rpartition(" | ")
            out[key.strip()] = why.strip()
    return out


def mutants_in_scope() -> list[tuple[Any, str]]:
    """(mutant, check) for every mutant of tools/mutants.py in a function of the scope."""
    import mutants  # tools/mutants.py (tools/ is on the path of tools/prove.py)
    sc = scope()
    out = []
    for path in sorted(CORE.glob("*.c")):
        for m in mutants.generate(path):
            if m.func in sc:
                out.append((m, sc[m.func]))
    return out


# The runs make prove's sample of mutants comes from: short ones. A caught mutant costs its
# run up to the goal it made false, then that goal's 40 s of CPU in each solver. Since issue
# 24's twentieth round the sample comes from `entry` (estop_fault, estop_tick, the TCP slots:
# 46 s alone under Typed), and its two are stop-path mutants (estop_fault's stop dropped,
# estop_tick's step dropped): 116 s for both at once on the idle machine, against 174 s for
# the two of `steps` (release's neutral test, stop_reason's TCP reason), which took 302 s and
# 193 s of a worker beside make test's other steps. Before: steps (Typed since the
# sixteenth round), udp until the fifteenth, clock under Caveat (a mutant of advance_clock
# 142 s beside make test). make prove-mutants tries them all.
SAMPLE_RUNS = ("entry",)


def sample(items: list[tuple[Any, str]], n: int, listed: frozenset[str] = frozenset()
           ) -> list[tuple[Any, str]]:
    """n mutants spread over the list, the same ones every run (a fixed choice: make test
    must not turn red on a commit that changed nothing of the core), drawn from the mutants
    of SAMPLE_RUNS (or from all, where those have none) that are not listed equivalent (one
    such tries nothing the list does not already say: after estop_udp.c was split off, the
    renamed stop's keys drew estop_fault's listed counter mutant into the sample)."""
    if n < 0:
        return []
    if n == 0 or n >= len(items):
        return items
    tried = [it for it in items if it[0].key not in listed]
    cheap = [it for it in tried if it[1].split(":")[1] in SAMPLE_RUNS]
    ranked = sorted(cheap or tried, key=lambda it: hashlib.sha256(
        it[0].key.encode()).hexdigest())
    return ranked[:n]


def compiles(core_dir: Path, file: str) -> bool:
    proc = subprocess.run(["gcc", "-std=c99", "-fsyntax-only", "-w", f"-I{core_dir}",
                           str(core_dir / file)], capture_output=True, timeout=60)
    return proc.returncode == 0


def goal_prop(goal: str, fcts: list[str]) -> str | None:
    """The label of the ensures or assert clause a goal of fcts' run proves (its -wp-prop), or
    None where the goal's name shows none (WP names a goal tag + function + kind + label, and
    a label's second clause label_2; wp.goal_function finds the function)."""
    model = wp.model_of(fcts)
    fct = wp.goal_function(goal, model, fcts)
    if fct is None:
        return None
    rest = goal.removeprefix(f"{wp.MODEL_TAGS[model]}{fct}_")
    m = re.fullmatch(r"(?:ensures|assert)_([A-Za-z]\w*?)(?:_\d+)?", rest)
    return m.group(1) if m else None


def run_mutant(name: str, core_dir: Path, fcts: list[str], env: dict[str, str],
               timeout_s: int = GOAL_TIMEOUT_S) -> wp.WpResult:
    """make prove's two passes on a mutant, at timeout_s of CPU a goal (mutant_timeout_s):
    CVC4 alone over the run (wp.first_pass_provers), stopped at its first failure; then Z3
    alone on the goal CVC4 left. A smoke test CVC4 fails, or a goal both solvers leave,
    catches it. Where Z3 proves that goal, or its clause has no label to select it by, one
    pass with both solvers over the run decides, stopped at its first failure, as before issue
    24's thirty-third round: there a sampled mutant cost 66 to 108 CPU-s alone on the idle
    machine (an unmutated estop_fault 86 CPU-s: Z3 ran out its limit on goals CVC4 proves at
    once). A retry with both solvers over the run costs as much: WP's cache does not keep a
    goal's failure for the next run."""
    (wp.WP_CACHE / name).mkdir(parents=True, exist_ok=True)
    provers = wp.first_pass_provers(fcts)
    first = wp.run_wp(name, core_dir, fcts, env, timeout_s, cache=True, first_failure=True,
                      provers=provers)
    if first.error or not first.failed or any(wp.SMOKE_TAG in g for g in first.failed):
        return first  # refused; not caught; or a smoke test CVC4 failed: caught
    if provers == wp.PROVERS:
        return first  # both solvers left it already
    prop = goal_prop(first.failed[0], fcts)
    if prop is not None:
        z3 = wp.run_wp(name, core_dir, fcts, env, timeout_s, only_prop=prop, provers="z3",
                       log_name=f"{name}-z3")
        if not z3.error and first.failed[0] in z3.failed:
            return first
    return wp.run_wp(name, core_dir, fcts, env, timeout_s, cache=True, first_failure=True,
                     log_name=f"{name}-both")


def try_mutant(index: int, mutant: Any, check: str, env: dict[str, str]) -> MutantTry:
    key = mutant.key
    file = mutant.file
    src = (CORE / file).read_text()
    core_dir = BUILD / f"mutant-{index}"
    if core_dir.exists():
        shutil.rmtree(core_dir)
    shutil.copytree(CORE, core_dir)
    (core_dir / file).write_text(mutant.apply(src))
    if not compiles(core_dir, file):
        shutil.rmtree(core_dir, ignore_errors=True)
        return MutantTry(key, check, False, "does not compile (not a mutant)", tried=False)
    w = run_mutant(f"mutant-{index}", core_dir, wp_fcts(check), env, mutant_timeout_s(check))
    shutil.rmtree(core_dir, ignore_errors=True)
    failed = w.failed + w.smoke_failed
    if w.error:
        return MutantTry(key, check, False, f"frama-c refuses it ({w.error[:80]})",
                         tried=False)
    if failed:
        return MutantTry(key, check, True, f"{len(failed)} goals fail, e.g. {failed[0]}")
    return MutantTry(key, check, False, f"{w.proved}/{w.total} goals proved")
