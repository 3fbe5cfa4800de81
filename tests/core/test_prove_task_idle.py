"""tools/proof/task_idle.ml: every WP run of make prove polls its solver calls every 2 ms, not
Frama-C's 50 ms (issue 24's forty-seventh round: with one call at a time a run stood idle for a
fifth to a third of its time). Real frama-c runs, with OCaml probes loaded beside the script."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from test_prove_tool import prove

from repo import ROOT

TASK_IDLE = ROOT / "tools" / "proof" / "task_idle.ml"
# 20 rounds of Task.on_idle's loop, timed inside frama-c (its start-up is not counted).
PROBE = """let () =
  let n = ref 0 in
  let t0 = Unix.gettimeofday () in
  !Task.on_idle (fun () -> incr n; !n < 20);
  Printf.printf "idle-probe %d rounds %.3f s\\n%!" !n (Unix.gettimeofday () -. t0)
"""


def needs_frama_c() -> None:
    if shutil.which("frama-c") is None or shutil.which("ocamlfind") is None:
        pytest.skip("no frama-c or ocamlfind here (scripts/ensure-debs prove)")


def idle_rounds_s(tmp_path: Path, *scripts: Path) -> float:
    probe = tmp_path / "idle_probe.ml"
    probe.write_text(PROBE)
    args = [a for s in (*scripts, probe) for a in ("-load-script", str(s))]
    out = subprocess.run(["frama-c", *args], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    m = re.search(r"idle-probe 20 rounds ([\d.]+) s", out.stdout)
    assert m, out.stdout + out.stderr
    return float(m.group(1))


def test_the_script_shortens_frama_cs_wait_between_polls(tmp_path: Path) -> None:
    """Frama-C alone sleeps 50 ms a round (1 s for 20: the control, which shows the probe can
    tell); with the script, 2 ms (about 0.04 s for 20; the bound leaves room for a loaded
    machine)."""
    needs_frama_c()
    assert idle_rounds_s(tmp_path) >= 0.9
    assert idle_rounds_s(tmp_path, TASK_IDLE) < 0.5


def test_every_wp_run_loads_the_script(tmp_path: Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """wp.run_wp loads wp.TASK_IDLE: a stand-in script that prints a mark is in the run's log
    (the lemmas run, a few seconds)."""
    from proof import frama  # tools/ is on the path (test_prove_tool loads prove)

    needs_frama_c()
    assert prove.wp.TASK_IDLE == TASK_IDLE
    mark = tmp_path / "mark.ml"
    mark.write_text('let () = print_endline "task-idle-loaded"\n')
    monkeypatch.setattr(prove.wp, "TASK_IDLE", mark)
    monkeypatch.setattr(frama, "BUILD", tmp_path)  # its own why3.conf
    monkeypatch.setattr(prove.wp, "BUILD", tmp_path)  # its own log, beside make prove's
    lemmas = prove.wp.LEMMAS
    res = prove.wp.run_wp(lemmas, frama.CORE, dict(prove.wp.wp_groups())[lemmas],
                          frama.why3_env(), provers=prove.wp.PROVERS)
    assert res.error == "" and res.proved == res.total > 0
    assert "task-idle-loaded" in (tmp_path / f"wp-{lemmas}.log").read_text()
