"""tools/proof/parsed.py: make prove parses firmware/core once, and each WP run over it loads the
saved state instead of parsing (issue 24's fiftieth round). A loaded state must give WP the very
code and contracts that the parse gives, and a run over other sources (a planted copy, an edit
made since) or with another frama-c must parse them, never load a state saved before."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from test_prove_tool import prove


def needs_frama_c() -> None:
    if shutil.which("frama-c") is None:
        pytest.skip("no frama-c here (scripts/ensure-debs prove)")


def printed(tmp_path: Path, name: str, head: list[str]) -> str:
    """The code with its ACSL annotations as Frama-C holds it after head (-print)."""
    out = tmp_path / f"{name}.c"
    res = subprocess.run(["frama-c", *head, "-print", "-ocode", str(out)], capture_output=True,
                         text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-500:] + res.stderr[-500:]
    return out.read_text()


def test_a_loaded_state_holds_what_the_parse_gives(tmp_path: Path) -> None:
    needs_frama_c()
    core = prove.frama.CORE
    parse = prove.wp.parse_args(core)
    stale = tmp_path / "parsed-0123456789abcdef.sav"  # of sources since edited
    stale.write_bytes(b"")
    state = prove.parsed.save(core, parse, dict(os.environ), into=tmp_path)
    assert sorted(tmp_path.glob("parsed-*")) == [state]
    head = prove.parsed.head(core, parse, tmp_path)
    assert head == ["-load", str(state)]
    loaded = printed(tmp_path, "loaded", head)
    assert "requires" in loaded and "estop_udp_rx" in loaded  # the contracts and the code
    assert loaded == printed(tmp_path, "parsed", parse)


def test_a_run_over_other_sources_parses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    core = tmp_path / "core"
    shutil.copytree(prove.frama.CORE, core, ignore=shutil.ignore_patterns("build", "*.o"))
    parse = prove.wp.parse_args(core)
    states = tmp_path / "states"
    states.mkdir()
    assert prove.parsed.head(core, parse, states) == parse  # no state saved
    state = prove.parsed.state_path(core, parse, states)
    state.write_bytes(b"")  # a state of these very sources (what save leaves)
    assert prove.parsed.head(core, parse, states) == ["-load", str(state)]
    # the same arguments, a source or a header edited since: parsed again
    for name in ("estop_crc.c", "estop_internal.h"):
        state = prove.parsed.state_path(core, parse, states)
        state.write_bytes(b"")
        assert prove.parsed.head(core, parse, states) == ["-load", str(state)]
        src = core / name
        src.write_text(src.read_text() + "/* edited */\n")
        assert prove.parsed.head(core, parse, states) == parse, name
    # another frama-c (an upgrade) never loads a state the one before saved
    state = prove.parsed.state_path(core, parse, states)
    state.write_bytes(b"")
    other = tmp_path / "bin"
    other.mkdir()
    (other / "frama-c").write_text("#!/bin/sh\n")
    (other / "frama-c").chmod(0o755)
    monkeypatch.setenv("PATH", f"{other}{os.pathsep}{os.environ['PATH']}")
    assert prove.parsed.head(core, parse, states) == parse
    monkeypatch.undo()
    assert prove.parsed.head(core, parse, states) == ["-load", str(state)]
    # the core of make prove never loads the state of a copy (other paths, other digest)
    core_parse = prove.wp.parse_args(prove.frama.CORE)
    assert prove.parsed.head(prove.frama.CORE, core_parse, states) == core_parse
