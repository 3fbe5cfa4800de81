"""tools/proof/task_idle.ml: every WP run of make prove polls its solver calls every 2 ms, not
Frama-C's 50 ms (issue 24's forty-seventh round: with one call at a time a run stood idle for a
fifth to a third of its time). Real frama-c runs, with OCaml probes loaded beside the module."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_prove_tool import prove

from repo import ROOT

# 20 rounds of Task.on_idle's loop, timed inside frama-c (its start-up is not counted).
PROBE = """let () =
  let n = ref 0 in
  let t0 = Unix.gettimeofday () in
  !Task.on_idle (fun () -> incr n; !n < 20);
  Printf.printf "idle-probe %d rounds %.3f s\\n%!" !n (Unix.gettimeofday () -. t0)
"""


def needs_frama_c() -> None:
    if shutil.which("frama-c") is None or shutil.which("ocamlopt") is None:
        pytest.skip("no frama-c or ocamlopt here (scripts/ensure-debs prove)")


def idle_rounds_s(tmp_path: Path, *sources: Path) -> float:
    probe = tmp_path / "idle_probe.ml"
    probe.write_text(PROBE)
    mods = [str(prove.wp.task_idle.module(s, tmp_path)) for s in (*sources, probe)]
    out = subprocess.run(["frama-c", "-load-module", ",".join(mods)], capture_output=True,
                         text=True, timeout=120, cwd=tmp_path)
    m = re.search(r"idle-probe 20 rounds ([\d.]+) s", out.stdout)
    assert m, out.stdout + out.stderr
    return float(m.group(1))


def test_the_module_shortens_frama_cs_wait_between_polls(tmp_path: Path) -> None:
    """Frama-C alone sleeps 50 ms a round (1 s for 20: the control, which shows the probe can
    tell); with the module, 2 ms (about 0.06 s for 20; the bound leaves room for a loaded
    machine)."""
    needs_frama_c()
    assert idle_rounds_s(tmp_path) >= 0.9
    assert idle_rounds_s(tmp_path, prove.wp.task_idle.SOURCE) < 0.5


def test_every_wp_run_loads_the_module(tmp_path: Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """wp.run_wp loads wp.TASK_IDLE's module: a stand-in that prints a mark is in the run's log
    (the lemmas run, a few seconds)."""
    from proof import frama  # tools/ is on the path (test_prove_tool loads prove)

    needs_frama_c()
    assert prove.wp.TASK_IDLE == ROOT / "tools" / "proof" / "task_idle.ml"
    mark = tmp_path / "mark.ml"
    mark.write_text('let () = print_endline "task-idle-loaded"\n')
    monkeypatch.setattr(prove.wp, "TASK_IDLE", mark)
    monkeypatch.setattr(frama, "BUILD", tmp_path)  # its own why3.conf
    monkeypatch.setattr(prove.wp, "BUILD", tmp_path)  # its own log and module, beside make prove's
    lemmas = prove.wp.LEMMAS
    res = prove.wp.run_wp(lemmas, frama.CORE, dict(prove.wp.wp_groups())[lemmas],
                          frama.why3_env(), provers=prove.wp.PROVERS)
    assert res.error == "" and res.proved == res.total > 0
    assert "task-idle-loaded" in (tmp_path / f"wp-{lemmas}.log").read_text()


BUILD_ONE = """import sys
sys.path.insert(0, sys.argv[1])
from proof import task_idle
from pathlib import Path
print(task_idle.module(task_idle.SOURCE, Path(sys.argv[2])))
"""


def test_runs_that_start_together_each_get_the_whole_module(tmp_path: Path) -> None:
    """Four processes build the module at once into one directory (make prove's two workers and
    the self-test start WP runs together; frama-c -load-script raced there): each prints the
    same module, which frama-c loads, and no build directory is left behind."""
    needs_frama_c()
    procs = [subprocess.Popen([sys.executable, "-c", BUILD_ONE, str(ROOT / "tools"),
                               str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(4)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    paths = {out.strip() for out, _ in outs}
    assert len(paths) == 1, paths
    module = Path(paths.pop())
    assert [p.name for p in tmp_path.iterdir()] == [module.name]
    res = subprocess.run(["frama-c", "-load-module", str(module)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr


def test_a_module_that_does_not_build_is_one_line_naming_the_compiler(tmp_path: Path) -> None:
    """A script the compiler refuses (a Frama-C whose Task has no on_idle, say) raises one line
    that names ocamlopt and its message: make prove prints it once and stops (tools/prove.py)."""
    needs_frama_c()
    broken = tmp_path / "broken.ml"
    broken.write_text("let () =\n  Task.no_such_hook := ()\n")
    with pytest.raises(RuntimeError) as err:
        prove.wp.task_idle.module(broken, tmp_path / "build")
    msg = str(err.value)
    assert "\n" not in msg and "ocamlopt" in msg and "no_such_hook" in msg, msg
