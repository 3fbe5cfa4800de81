"""A goal's SMT problem asked of CVC4 with its assertions in several orders: a check that a
goal's verdict does not hang on one order (issue 24's forty-third round).

A WP goal's problem is the same logic in any order of its assertions, but CVC4's search is
not: `estop_tcp_rx`'s `leaves_stopped_only_by_release` took 19 s in one `make prove` and ran
out of 90 s, then of the retry's 300 s, in another (the CI run of fcfba03), with no change to
the code; WP's simplifier does not number its terms the same way in every run. Asked alone
with its assertions in 8 orders, 6 ran out of 90 s. A goal that passes every order is not
proved robust, but one that fails an order is shown fragile.

The problems come from tools/proof/solvers/cpu-limited, which copies each SMT file it is given
into $ESTOP_CAPTURE_DIR when that is set.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from proof import frama, wp
from proof.reorder import reordered


@dataclasses.dataclass
class Answer:
    seed: int
    proved: bool
    cpu_s: float


def ask(problem: str, seeds: range, cpu_s: int) -> list[Answer]:
    """CVC4 on the problem in each order of seeds, each as make prove asks a goal of it
    (tools/proof/solvers/cpu-limited: its options, cpu_s of CPU time), up to the first order
    it does not prove (a fragile goal costs one limit, not one a seed)."""
    answers: list[Answer] = []
    with tempfile.TemporaryDirectory(prefix="orders-") as d:
        for seed in seeds:
            f = Path(d) / f"s{seed}.smt2"
            f.write_text(reordered(problem, seed))
            t0 = os.times()
            try:
                # through the wrapper make prove's goals go through (its options, its limit)
                p = subprocess.run(
                    [str(frama.SOLVERS / "cvc4"), "--lang=smt2", str(f)],
                    env=dict({k: v for k, v in os.environ.items()
                              if not k.startswith("ESTOP_")}, ESTOP_SOLVER_CPU_S=str(cpu_s)),
                    capture_output=True, text=True, check=False, timeout=cpu_s * wp.WALL_GUARD)
                proved = p.stdout.startswith("unsat")
            except subprocess.TimeoutExpired:
                proved = False
            t1 = os.times()
            answers.append(Answer(seed, proved, t1.children_user - t0.children_user
                                  + t1.children_system - t0.children_system))
            if not proved:
                break
    return answers


def run_options(fct: str) -> list[str]:
    """The options (%flag, @Model) of the make prove run that proves fct: its problems are
    written as that run writes them (clock's %ground and %noprune change them)."""
    for _, fcts in wp.wp_groups():
        if fct in fcts:
            return wp.run_flags(fcts)
    return ["@Typed"]


def problems(core: Path, fct: str, prop: str) -> list[str]:
    """The SMT problems WP gives CVC4 for the clauses named prop of fct, asked alone with the
    options of its run (each call cut at 1 s: the problem is copied as the call starts)."""
    if shutil.which("cvc4") is None or shutil.which("frama-c") is None:
        raise RuntimeError("no frama-c or cvc4 here (scripts/ensure-debs prove)")
    with tempfile.TemporaryDirectory(prefix="capture-") as d:
        env = dict(frama.why3_env(), ESTOP_CAPTURE_DIR=d)
        wp.run_wp(f"orders-{fct}", core, [fct, *run_options(fct)], env, 1, provers="cvc4",
                  only_prop=prop)
        return [f.read_text() for f in sorted(Path(d).glob("cvc4-*.smt2"))]
