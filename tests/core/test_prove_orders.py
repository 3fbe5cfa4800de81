"""tools/proof/orders.py: a WP goal's SMT problem asked of CVC4 with its assertions in other
orders, so that a goal whose verdict hangs on one order fails here and not in one CI run of
make prove out of several (docs/PROOF.md "Known holes")."""

from __future__ import annotations

import importlib
import shutil
import sys
from pathlib import Path

import pytest

from repo import ROOT

sys.path.insert(0, str(ROOT / "tools"))  # tools/proof/ is a package there
orders = importlib.import_module("proof.orders")
reorder = importlib.import_module("proof.reorder")
frama = importlib.import_module("proof.frama")
wp = importlib.import_module("proof.wp")

SMT = """(set-logic ALL)
; a comment (with a parenthesis
(declare-fun a () Int)
(assert (> a 0))
(declare-fun |b c| () Int)
(assert (= |b c| (+ a 1)))
(assert (distinct "x)"  "y""z"))
(assert (not (> |b c| 1)))
(check-sat)
(get-info :reason-unknown)
"""


def test_an_order_keeps_every_declaration_before_the_assertions_and_the_end_last() -> None:
    cmds = reorder.commands(SMT)
    assert len(cmds) == 9 and cmds[5] == '(assert (distinct "x)"  "y""z"))'
    for seed in range(6):
        out = reorder.commands(reorder.reordered(SMT, seed))
        assert sorted(out) == sorted(cmds)
        assert out[:3] == ["(set-logic ALL)", "(declare-fun a () Int)",
                           "(declare-fun |b c| () Int)"]
        assert out[-2:] == ["(check-sat)", "(get-info :reason-unknown)"]
    assert reorder.commands(reorder.reordered(SMT, 0))[3:7] == [c for c in cmds if "assert" in c]
    assert {tuple(reorder.commands(reorder.reordered(SMT, s))) for s in range(6)} != {tuple(cmds)}


def test_a_problem_is_proved_in_every_order_and_a_false_one_in_none() -> None:
    if shutil.which("cvc4") is None:
        pytest.skip("no cvc4 here (scripts/ensure-debs prove)")
    assert [a.proved for a in orders.ask(SMT, range(3), 10)] == [True] * 3
    false = SMT.replace("(not (> |b c| 1))", "(not (> |b c| 2))")
    assert [a.proved for a in orders.ask(false, range(2), 10)] == [False]  # the first only


# The goals fixed for this (issue 24's forty-third round), each with what failed before.
# - estop_tcp_rx's release rule took 19 s in one make prove and failed both passes of another
#   (the CI run of fcfba03); on fcfba03 3 of these 4 orders ran out of 90 s. finish_frame now
#   states what estop__finish keeps of the frame, and finished_release carries the rule past
#   it: about 3 s in every order.
# - estop__handle_msg's msg_inv_3 (slots_ok after the step) took 13 s in make prove's run, ran
#   out of 90 s asked alone, and in the first of these orders; msg_slots now asserts it one
#   branch at a time: 0.2 s.
# - valid_body's body_keeps_link (the forty-fifth round): its second problem took 7, 5 and 41 s
#   in the first three of these orders and ran out of 90 s in the fourth, past the three
#   branches of a keyed unit; they are now keyed_body's, and valid_body meets one call: its
#   problems take under a second.
# - tag_right's made (the forty-fifth round): 5 s in the first of these orders, out of 90 s in
#   the second. Its MAC clause (estop_b2s_mac's mac_value) holds for a length in 1..64 and a
#   multiple of 4, which the solvers had to find from tag_at being 32 or 44; made_len now
#   asserts it (0.2 s): made takes about 5 s in every order.
FIXED = [("estop_tcp_rx", "leaves_stopped_only_by_release"), ("estop__handle_msg", "msg_inv"),
         ("valid_body", "body_keeps_link"), ("tag_right", "made")]


@pytest.mark.parametrize(("fct", "prop"), FIXED)
def test_a_goal_that_hung_on_its_order_is_proved_in_every_order(
        fct: str, prop: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The goal's problems, asked of CVC4 with their assertions in 4 orders, each under make
    prove's 90 s of CPU (the first order that fails ends the test)."""
    if shutil.which("frama-c") is None or shutil.which("cvc4") is None:
        pytest.skip("no frama-c or cvc4 here (scripts/ensure-debs prove)")
    monkeypatch.setattr(frama, "BUILD", tmp_path)  # its own why3.conf and log, beside make
    monkeypatch.setattr(wp, "BUILD", tmp_path)  # prove's
    found = orders.problems(frama.CORE, fct, prop)
    assert found, f"no problem of {fct}'s {prop} reached CVC4"
    for problem in found:
        answers = orders.ask(problem, range(4), wp.GOAL_TIMEOUT_S)
        assert [a.proved for a in answers] == [True] * 4, answers


def wrapped_cvc4(problem: Path, orders_n: int, cpu_s: int) -> tuple[int, str]:
    import subprocess
    env = {"PATH": "/usr/bin:/bin", "ESTOP_SOLVER_CPU_S": str(cpu_s),
           "ESTOP_SOLVER_ORDERS": str(orders_n)}
    p = subprocess.run([str(ROOT / "tools" / "proof" / "solvers" / "cvc4"), "--lang=smt2",
                        f"--tlimit={cpu_s * 10000}", str(problem)], capture_output=True,
                       text=True, env=env, timeout=cpu_s * 10, check=False)
    return p.returncode, p.stdout


def test_the_retrys_cvc4_proves_in_its_first_order_and_fails_in_every_order(
        tmp_path: Path) -> None:
    """tools/proof/solvers/cpu-limited with ESTOP_SOLVER_ORDERS (make prove's retry): a true
    goal answered "unsat" as CVC4 answers it; a false one tried in every order, then answered
    as CVC4 answered the last (never "unsat"), and no reordered copy left beside it."""
    if shutil.which("cvc4") is None:
        pytest.skip("no cvc4 here (scripts/ensure-debs prove)")
    true, false = tmp_path / "true.smt2", tmp_path / "false.smt2"
    true.write_text(SMT)
    false.write_text(SMT.replace("(not (> |b c| 1))", "(not (> |b c| 2))"))
    rc, out = wrapped_cvc4(true, 4, 8)
    assert (rc, out.split()[0]) == (0, "unsat")
    rc, out = wrapped_cvc4(false, 4, 8)
    assert out.split()[0] == "sat"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["false.smt2", "true.smt2"]


def test_the_retrys_cvc4_goes_on_to_the_next_order_until_one_proves(tmp_path: Path) -> None:
    """The wrapper's loop, with a stand-in for CVC4 on PATH that proves only the third order
    and names each problem it is given: the goal's own order first, then the reordered
    copies, each bounded by its share of the CPU time, and the answer of the one that proved."""
    import subprocess
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    stand_in = bin_dir / "cvc4"
    stand_in.write_text('#!/bin/sh\nfor a; do f=$a; done\n'
                        'echo "$f $(ulimit -t)" >> "$CALLS"\n'
                        'case $f in *.order2.smt2) echo unsat ;; *) echo unknown ;; esac\n')
    stand_in.chmod(0o755)
    problem = tmp_path / "goal.smt2"
    problem.write_text(SMT)
    calls = tmp_path / "calls"
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "ESTOP_SOLVER_CPU_S": "300",
           "ESTOP_SOLVER_ORDERS": "4", "CALLS": str(calls)}
    p = subprocess.run([str(ROOT / "tools" / "proof" / "solvers" / "cvc4"), "--lang=smt2",
                        str(problem)], capture_output=True, text=True, env=env, timeout=60,
                       check=False)
    assert (p.returncode, p.stdout) == (0, "unsat\n")
    assert calls.read_text().splitlines() == [
        f"{problem} 150", f"{problem}.order1.smt2 50", f"{problem}.order2.smt2 50"]
    assert sorted(f.name for f in tmp_path.iterdir()) == ["bin", "calls", "goal.smt2"]
    env["ESTOP_SOLVER_ORDERS"] = "1"  # make prove's first pass: the one order, all the time
    calls.unlink()
    p = subprocess.run([str(ROOT / "tools" / "proof" / "solvers" / "cvc4"), "--lang=smt2",
                        str(problem)], capture_output=True, text=True, env=env, timeout=60,
                       check=False)
    assert p.stdout == "unknown\n" and calls.read_text().splitlines() == [f"{problem} 300"]


def test_a_goal_is_captured_with_the_options_of_its_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """orders.problems writes a goal's problem as make prove's run of its function writes it:
    clock's %ground and %noprune (without them, a clock goal was another problem)."""
    if shutil.which("cvc4") is None or shutil.which("frama-c") is None:
        pytest.skip("no frama-c or cvc4 here (scripts/ensure-debs prove)")
    asked: list[list[str]] = []
    monkeypatch.setattr(orders.wp, "run_wp", lambda name, core, fcts, *a, **k: asked.append(fcts))
    for fct in ("advance_clock", "estop_tcp_rx", "handle_frame"):
        assert orders.problems(ROOT / "firmware" / "core", fct, "x") == []
    assert asked == [["advance_clock", "@Typed", "%noprune", "%ground"],
                     ["estop_tcp_rx", "@Typed"], ["handle_frame", "@Typed", "%split"]]
