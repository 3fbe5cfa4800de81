"""`make prove`: the firmware core under Frama-C (docs/PROOF.md).

1. Eva: prove/eva_driver.c calls every entry point in any order with unknown inputs, once for
   a unit with a key (TCP chunks of every length) and once for one without (whole frames).
   Every alarm fails the run; so does a function of firmware/core that the driver does not
   reach, and a rule of the driver (an assertion rule_*) that Eva does not show valid. Prints
   the alarms, the functions and statements reached, and the rules.
2. WP: the ACSL contracts of firmware/core (per group of functions, in parallel runs) and the
   lemmas, proved by Qed (WP's own simplifier) and the SMT solvers through Why3. Every goal must
   be proved; a run under Typed also passes its smoke tests and checks its model's hypotheses.
   What the proofs assume (axioms, admitted clauses) is printed, each with the test that would
   fail were it false (prove/assumed.txt).
3. Self-test: the same analyses on copies of the core with a planted fault each (an
   out-of-bounds write, a wrong release path, ...) and on mutants of the lines that decide a
   state change; each must fail, or the set-up is broken (a missing prover, a driver that no
   longer reaches the code, a contract that says nothing) and so is the run.
Exit status 0 when all three hold.

  tools/prove.py                       the whole of make prove (a fixed sample of mutants)
  tools/prove.py --only mutants --mutants 0      every mutant of the scope (make prove-mutants)
  tools/prove.py --only mutants --mutants 20     the first 20 of the fixed order
"""

from __future__ import annotations

import argparse
import concurrent.futures
import functools
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

from proof import assumed, eva, frama, parsed, selftest, task_idle, wp
from proof.frama import BUILD, CORE, ROOT, TOOLS, core_functions, why3_env
from proof.wp import MODEL_CHECKS, WpResult, parse_checks  # noqa: F401 - tests use them

MUTANTS_IN_MAKE_PROVE = 2  # the fast subset; make prove-mutants runs them all
# The order make prove starts its analyses in on its two workers: the longest first, so that
# the short ones fill both workers at the end (in file order, the two-minute loops run was
# among the last to start while the plants waited). The figures are each analysis's seconds on
# the idle machine with the first pass of CVC4 alone (issue 24: tools/prove.py, and the runs
# datagram and valid on their own); only the order depends on them. One not named here counts
# as DEFAULT_COST_S. wp:frame and wp:plain are theirs beside other runs of issue 24's
# thirty-first round (32 and 22 s); wp:tcpframe, wp:reqstep and wp:auth theirs alone on the
# idle machine in the thirty-sixth (68, 76 and 45 s of wall time with two solvers at once);
# wp:udp its own with %noprune (the thirtieth); wp:clock (145 s alone since the twenty-ninth, 244 s
# before) and wp:loops theirs scaled by what %noprune saved alone (the thirty-second: 80 s
# against 106, 22 s against 26); the Eva runs theirs with exact_call, a mutant its own in two
# passes (the thirty-third).
COST_S = {"eva:keyed": 68, "wp:tcp": 123, "wp:tcpframe": 50, "wp:reqstep": 70, "wp:clock": 109,
          "wp:valid": 28, "wp:plain": 22, "wp:frame": 32,
          "wp:auth": 45, "wp:datagram": 66, "mutant": 30, "wp:loops": 50, "wp:init": 30,
          "eva:plain": 48, "wp:entry": 46, "wp:steps": 113, "plant:eva": 25, "plant:wp": 20,
          "wp:udp": 31, "wp:frames": 26, "wp:link": 11, "wp:ct": 9, "wp:lemmas": 4,
          "wp:blake2s": 20}
DEFAULT_COST_S = 60
# Why this make prove failed, and which goals needed the retry, each in a line: main prints them
# again last, as CI keeps only the end of a log (the CI run of fcfba03 showed the self-test's
# lines and "FAILED", and not which goal had failed 20 lines up).
WHY_FAILED: list[str] = []
RETRIED: list[str] = []


def cost_s(key: str) -> int:
    return COST_S.get(key, DEFAULT_COST_S)


def cpu_line(runs: list[tuple[str, float]]) -> str:
    """The CPU time of the Frama-C runs by part (a run's log names it: eva-<run>.log,
    wp-<group>.log and its retry, the self-test's wp-planted-*, eva-planted-* and wp-mutant-*)."""
    parts = {"wp": 0.0, "eva": 0.0, "self-test": 0.0}
    for log, cpu in runs:
        part = ("self-test" if "planted" in log or "mutant" in log else
                "eva" if log.startswith("eva-") else "wp")
        parts[part] += cpu
    return (f"prove: CPU time of frama-c and its solvers: {sum(parts.values()):.0f} s ("
            + ", ".join(f"{k} {v:.0f}" for k, v in parts.items()) + ")")


def report_eva(evas: list[concurrent.futures.Future[eva.EvaResult]]) -> bool:
    ok = True
    for fut in evas:
        r = fut.result()
        reached = sum(1 for f in r.functions.values() if f[0] > 0)
        stmts = sum(f[0] for f in r.functions.values())
        all_stmts = sum(f[1] for f in r.functions.values())
        core_fns = core_functions(CORE)
        core_reached = sum(1 for f in core_fns if r.functions.get(f, (0, 1))[0] > 0)
        core_st = sum(r.functions.get(f, (0, 0))[0] for f in core_fns)
        core_all = sum(r.functions.get(f, (0, 0))[1] for f in core_fns)
        print(f"prove: eva {r.name} ({r.cpu_s:.0f} CPU-s): {len(r.alarms)} alarms; core "
              f"functions reached "
              f"{core_reached}/{len(core_fns)}, core statements reached {core_st}/"
              f"{core_all} ({100.0 * core_st / max(core_all, 1):.1f} %); with the driver "
              f"{reached} functions, {stmts}/{all_stmts} statements; rules shown "
              f"{len(r.rules) - len(r.rules_not_shown)}/{len(r.rules)}")
        for a in r.alarms:
            print(f"prove:   alarm: {a}")
        for rule in r.rules_not_shown:
            print(f"prove:   rule not shown: {rule}")
        if r.unreached:
            print(f"prove:   not reached in this run: {' '.join(r.unreached)}")
        if r.error:
            print(f"prove:   error: {r.error}")
        if r.alarms or r.error or r.rules_not_shown or not r.rules:
            WHY_FAILED.append(f"eva {r.name}: {len(r.alarms)} alarms, "
                              f"{len(r.rules_not_shown)} rules not shown"
                              + (f", {r.error}" if r.error else ""))
            ok = False
    if evas:
        never = set(core_functions(CORE))
        for fut in evas:
            never &= set(fut.result().unreached)
        if never:
            print(f"prove: eva: core functions no run reached: {' '.join(sorted(never))}")
            WHY_FAILED.append(f"eva: core functions no run reached: {' '.join(sorted(never))}")
        ok = ok and not never
    return ok


def report_wp(wps: list[concurrent.futures.Future[tuple[list[str], WpResult]]]) -> bool:
    ok = True
    totals: dict[str, int] = {}
    sums = [0, 0, 0, 0]  # proof goals proved, proof goals, smoke tests, failed smoke tests
    groups = dict(wp.wp_groups())
    for fut in wps:
        retried, w = fut.result()
        if retried:
            print(f"prove: wp {w.name}: {len(retried)} goals not proved by "
                  f"{wp.FIRST_PASS_PROVERS} in {wp.GOAL_TIMEOUT_S} s each ({' '.join(retried)}); "
                  f"their functions run again with {wp.PROVERS}, {wp.GOAL_RETRY_TIMEOUT_S} s each")
            RETRIED.append(f"{w.name}: {' '.join(retried)}")
        for k, v in w.by_prover.items():
            totals[k] = totals.get(k, 0) + v
        provers = ", ".join(f"{k} {v}" for k, v in sorted(w.by_prover.items()))
        model = wp.model_of(groups[w.name])
        proved, goals = wp.proof_goals(w)
        for i, v in enumerate((proved, goals, w.smoke, len(w.smoke_failed))):
            sums[i] += v
        checks = (f"; {w.smoke} smoke tests, {len(w.smoke_failed)} failed; memory-model "
                  "hypotheses checked at the calls" if model in MODEL_CHECKS else
                  "; no smoke tests, hypotheses not checked")
        print(f"prove: wp {w.name} ({model}): {proved}/{goals} proof goals proved "
              f"(WP's count {w.proved}/{w.total} with the smoke tests; {provers})"
              + checks + f"; {w.wall_s:.0f} s, {w.cpu_s:.0f} CPU-s")
        for g in w.failed:
            print(f"prove:   not proved: {g}")
        for g in w.smoke_failed:
            print(f"prove:   smoke test failed (a precondition that cannot hold, or code "
                  f"the proof finds dead): {g}")
        if w.smoke_unanswered:
            print(f"prove:   {w.smoke_unanswered} smoke tests passed that no solver answered "
                  "(it did not run: a smoke test then shows nothing)")
        for g in w.wrong_model[:5]:
            print(f"prove:   goal of another memory model than {model}: {g}")
        if w.error:
            print(f"prove:   error: {w.error}")
        if not wp.ok(w):
            WHY_FAILED.append(
                f"wp {w.name}: {proved}/{goals} proof goals proved"
                + "".join(f"; not proved: {g}" for g in w.failed[:3])
                + "".join(f"; smoke test failed: {g}" for g in w.smoke_failed[:3])
                + (f"; {w.smoke_unanswered} smoke tests no solver answered"
                   if w.smoke_unanswered else "")
                + (f"; {len(w.wrong_model)} goals of another model" if w.wrong_model else "")
                + (f"; error: {w.error}" if w.error else ""))
            ok = False
    if wps:
        print(f"prove: wp total: {sums[0]}/{sums[1]} proof goals proved, {sums[2]} smoke tests "
              f"({sums[3]} failed); WP's count by prover (a solver's count holds the smoke "
              "tests it answered; a goal both solvers proved counts for each): "
              + ", ".join(f"{k} {v}" for k, v in sorted(totals.items())))
    return ok


def report_assumed() -> bool:
    items, errors = assumed.check()
    for a in items:
        print(f"prove: assumed, not proved: {a.name} ({a.why}; tested by {a.test})")
    for e in errors:
        print(f"prove:   error: {e}")
        WHY_FAILED.append(f"assumed: {e}")
    return not errors


def report_mutants(tries: list[selftest.MutantTry], equivalent: dict[str, str],
                   in_scope: int) -> bool:
    """The self-test's mutants: each tried one caught, or listed as equivalent (and a listed
    one not caught). One that is not a mutant (does not compile) counts for neither; a sample
    of which none could be tried fails, as it showed nothing."""
    ok = True
    caught_n = 0
    tried_n = 0
    for t in tries:
        if not t.tried:
            print(f"prove: self-test mutant {t.key} ({t.check}): not tried: {t.what}")
            continue
        tried_n += 1
        listed = t.key in equivalent
        verdict = "caught" if t.caught else (
            "equivalent (listed)" if listed else "NOT CAUGHT")
        print(f"prove: self-test mutant {t.key} ({t.check}): {verdict}: {t.what}")
        caught_n += int(t.caught)
        ok = ok and (t.caught or listed)
        if not (t.caught or listed):
            WHY_FAILED.append(f"self-test mutant {t.key}: not caught")
        if t.caught and listed:
            print("prove:   error: listed as equivalent in prove/mutants_equivalent.txt, "
                  "but caught: take it off the list")
            WHY_FAILED.append(f"self-test mutant {t.key}: listed as equivalent, but caught")
            ok = False
    print(f"prove: self-test mutants caught {caught_n}/{tried_n} "
          f"(of {in_scope} in prove/mutants_scope.txt; "
          f"{sum(1 for t in tries if t.tried and t.key in equivalent)} listed equivalent; "
          f"{len(tries) - tried_n} not mutants, not tried)")
    if tried_n == 0:
        print("prove:   error: no mutant of the sample could be tried")
        WHY_FAILED.append("self-test: no mutant of the sample could be tried")
        ok = False
    return ok


def summary(ok: bool) -> list[str]:
    """The lines printed last: the goals that needed the retry (a slow or fragile goal, passed or
    not), and why the run failed (a failure with no reason recorded says so, not nothing)."""
    lines = [f"prove: needed the retry: {r}" for r in RETRIED]
    if not ok:
        lines += [f"prove: failed: {w}" for w in WHY_FAILED] or [
            "prove: failed: no reason recorded (see the lines above)"]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="analyses run at once (default 2)")
    ap.add_argument("--only", choices=["eva", "wp", "self-test", "mutants"], action="append",
                    help="run only these parts (repeatable; mutants: the self-test's mutants "
                         "without its plants)")
    ap.add_argument("--group", action="append", metavar="NAME",
                    help="with wp: run only these groups of prove/wp_groups.txt (repeatable)")
    ap.add_argument("--mutants", type=int, default=MUTANTS_IN_MAKE_PROVE, metavar="N",
                    help="with self-test: a fixed sample of N mutants (0: all of them, -1: none; "
                         f"default {MUTANTS_IN_MAKE_PROVE})")
    args = ap.parse_args()
    parts = set(args.only or ["eva", "wp", "self-test"])
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        print(f"prove: error: missing {', '.join(missing)} (scripts/ensure-debs prove)",
              file=sys.stderr)
        return 2
    BUILD.mkdir(parents=True, exist_ok=True)
    try:  # once, before the runs that load it: a failed build is one line, not one per run
        task_idle.module()
    except (RuntimeError, OSError, subprocess.SubprocessError) as err:
        print(f"prove: error: the module every WP run loads (tools/proof/task_idle.ml): {err}",
              file=sys.stderr)
        return 2
    shutil.rmtree(wp.WP_CACHE, ignore_errors=True)
    env = why3_env()
    if "wp" in parts:
        try:  # once, before the runs that load it (tools/proof/parsed.py)
            parsed.save(CORE, wp.parse_args(CORE), env)
        except (RuntimeError, OSError) as err:
            print(f"prove: error: the parse of firmware/core for the WP runs: {err}",
                  file=sys.stderr)
            return 2
    t0 = time.monotonic()
    ok = report_assumed()
    in_scope = selftest.mutants_in_scope() if parts & {"self-test", "mutants"} else []
    equivalent = selftest.equivalents()
    muts = selftest.sample(in_scope, args.mutants, frozenset(equivalent))
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        jobs: list[tuple[int, str, Callable[[], Any]]] = []
        if "eva" in parts:
            jobs += [(cost_s(f"eva:{n}"), f"eva:{n}", functools.partial(
                eva.run_eva, n, CORE, k, env, whole_chunks=w)) for n, k, w in eva.RUNS]
        if "wp" in parts:
            jobs += [(cost_s(f"wp:{n}"), f"wp:{n}", functools.partial(
                wp.run_wp_retrying, n, f, env)) for n, f in wp.wp_groups()
                     if not args.group or n in args.group]
        if "self-test" in parts:
            jobs += [(cost_s(f"plant:{c.split(':')[0]}"), f"plant:{c}:{copy}", functools.partial(
                selftest.run_plants, c, ps, env))
                     for (c, copy), ps in selftest.plant_checks().items()]
        jobs += [(cost_s("mutant"), f"mutant:{i}", functools.partial(
            selftest.try_mutant, i, m, c, env)) for i, (m, c) in enumerate(muts)]
        # The longest first (a stable sort: the others in the order above).
        futs = {key: pool.submit(fn) for _, key, fn in sorted(jobs, key=lambda j: -j[0])}
        keys = [key for _, key, _ in jobs]
        evas = [futs[k] for k in keys if k.startswith("eva:")]
        wps = [futs[k] for k in keys if k.startswith("wp:")]
        planted = [futs[k] for k in keys if k.startswith("plant:")]
        mutated = [futs[k] for k in keys if k.startswith("mutant:")]
        ok = report_eva(evas) and ok
        ok = report_wp(wps) and ok
        for fut in planted:
            for p, caught, what in fut.result():
                print(f"prove: self-test {p.name} ({p.check}): "
                      f"{'caught' if caught else 'NOT CAUGHT'}: {what}")
                if not caught:
                    WHY_FAILED.append(f"self-test {p.name} ({p.check}): not caught")
                ok = ok and caught
        if mutated:
            ok = report_mutants([f.result() for f in mutated], equivalent, len(in_scope)) and ok
            for err in selftest.mutant_limit_errors({k.split(":")[1]: futs[k].result()
                                                     for k in keys if k.startswith("wp:")}):
                print(f"prove:   error: {err}")
                WHY_FAILED.append(f"self-test: {err}")
                ok = False
    print(cpu_line(frama.CPU_RUNS))
    for line in summary(ok):
        print(line)
    print(f"prove: {'ok' if ok else 'FAILED'} in {time.monotonic() - t0:.0f} s "
          f"(logs in {BUILD.relative_to(ROOT)}/)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
