"""tools/prove.py's judgement of a WP log (docs/PROOF.md): the smoke tests and the memory model
of a run, on logs written here. Frama-C itself does not run (make prove runs it, and its
self-test plants faults in the core that only a smoke test catches)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from repo import ROOT


def load_prove() -> ModuleType:
    spec = importlib.util.spec_from_file_location("prove_tool", ROOT / "tools" / "prove.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


prove = load_prove()

GOOD = """[wp] [Qed] Goal typed_estop_ct_equal_ensures : Valid (3ms)
[wp] [CVC4 1.8] Goal typed_estop_ct_equal_assigns : Valid (Qed:2ms) (40ms) (7778)
[wp] [Passed] Smoke-test typed_estop_ct_equal_wp_smoke_default_requires
[wp] [Passed] Smoke-test typed_estop_ct_equal_wp_smoke_dead_code_s290
[wp] Proved goals:    4 / 4
"""


def checked(out: str, model: str = "Typed") -> Any:
    res = prove.WpResult("loops", 0, 0, {}, [], Path("wp-loops.log"))
    prove.parse_checks(res, out, model)
    return res


def test_a_clean_typed_run_passes() -> None:
    res = checked(GOOD)
    assert (res.smoke, res.smoke_failed, res.wrong_model) == (2, [], [])


def test_a_failed_smoke_test_is_a_failure() -> None:
    out = GOOD.replace("[Passed] Smoke-test typed_estop_ct_equal_wp_smoke_dead_code_s290",
                       "[Failed] Smoke-test typed_estop_ct_equal_wp_smoke_dead_code_s290")
    res = checked(out)
    assert res.smoke == 2
    assert res.smoke_failed == ["typed_estop_ct_equal_wp_smoke_dead_code_s290"]


def test_a_smoke_test_failed_by_one_prover_stays_failed() -> None:
    out = GOOD + "[wp] [Failed] Smoke-test typed_estop_ct_equal_wp_smoke_default_requires\n"
    assert checked(out).smoke_failed == ["typed_estop_ct_equal_wp_smoke_default_requires"]


def test_a_typed_run_that_is_also_caveat_is_refused() -> None:
    # The bug of the @Typed override: a second -wp-model added to Caveat named the goals so.
    res = checked(GOOD.replace("typed_estop", "typed_caveat_estop"))
    assert len(res.wrong_model) == 4


def test_a_caveat_run_is_named_typed_caveat() -> None:
    res = checked(GOOD.replace("typed_estop", "typed_caveat_estop"), "Caveat")
    assert res.wrong_model == []
    assert len(checked(GOOD, "Caveat").wrong_model) == 4


def test_every_typed_run_checks_hypotheses_and_smoke() -> None:
    assert {"-wp-check-memory-model", "-wp-smoke-tests"} <= set(prove.MODEL_CHECKS["Typed"])
