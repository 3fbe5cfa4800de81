"""The base install is pure Python: ``estop stop|status|release|lift|remote`` run with numpy,
dpkt, matplotlib, cffi, python-can, cantools and the C core all unimportable, against the real
estopd on loopback; the commands that need an extra say which. (A real fresh-venv ``pip
install .`` is measured by hand: see the report of issue 17; it needs PyPI for setuptools.)"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib

import pytest

from estop.unit.daemon import Daemon
from repo import ROOT

pytestmark = pytest.mark.timeout(120)
HEAVY = ("numpy", "dpkt", "matplotlib", "cffi", "_cffi_backend", "can", "cantools", "scipy",
         "estop._core")

# run estop's command line with the heavy modules made unimportable
BLOCKED = f"""
import importlib.abc, sys
HEAVY = {HEAVY!r}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name in HEAVY or name.split(".")[0] in HEAVY:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
        return None
sys.meta_path.insert(0, Block())
from estop.cli import main
code = main(sys.argv[1:])
leaked = sorted(m for m in sys.modules if m in HEAVY or m.split(".")[0] in HEAVY)
if leaked:
    sys.stderr.write(f"imported: {{leaked}}\\n")
    code = 99
sys.exit(code)
"""


def run_pure(*argv: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    return subprocess.run([sys.executable, "-c", BLOCKED, *argv], env=env, timeout=60,
                          capture_output=True, text=True, check=False)


def test_base_dependencies_are_none_and_extras_hold_the_rest() -> None:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = meta["project"]
    assert project["dependencies"] == []
    extras = project["optional-dependencies"]
    assert {"link", "bus", "dashboard", "test", "dev"} <= set(extras)
    assert any(d.startswith("numpy") for d in extras["link"])
    assert any(d.startswith("python-can") for d in extras["bus"])
    assert "cffi" not in " ".join(meta["build-system"]["requires"])


def test_the_tools_run_against_estopd_without_any_heavy_module(estopd: str) -> None:
    with Daemon([estopd]) as d:
        unit = ["--host", "127.0.0.1", "--tcp-port", str(d.tcp_port)]
        res = run_pure("status", *unit)
        assert res.returncode == 0 and res.stdout.startswith("ACK seq=1 state=STOPPED"), res
        res = run_pure("remote", *unit, "--udp-port", str(d.udp_port), "-q", "--script",
                       "hold 0.2; release; expect ack armed; lift; wait 0.05; status; "
                       "expect stopped lift")
        assert res.returncode == 0, res
        res = run_pure("stop", *unit, "--udp-port", str(d.udp_port))
        assert res.returncode == 0 and "ACK" in res.stdout and "STOPPED" in res.stdout, res
        res = run_pure("release", *unit)
        assert res.returncode == 1 and "nak=" in res.stdout, res  # an answer: no live link
        res = run_pure("lift", *unit, "--udp-port", str(d.udp_port))
        assert res.returncode == 0, res


@pytest.mark.parametrize("argv, extra", [
    (["link", "x.txt"], "link"),
    (["monitor", "--interface", "virtual"], "bus"),
])
def test_a_command_needing_an_extra_names_it(argv: list[str], extra: str) -> None:
    res = run_pure(*argv)
    assert res.returncode == 5
    assert res.stderr.strip().endswith(f"pip install 'estop[{extra}]'"), res
