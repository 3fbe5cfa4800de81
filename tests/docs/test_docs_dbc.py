"""The ESTOP_STATUS layout is written once, in the DBC; docs/PROTOCOL.md's table is generated
from it (tools/dbc_table.py) and must be exactly what the generator prints now."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from repo import ROOT

sys.path.insert(0, str(ROOT / "tools"))

import dbc_table  # noqa: E402


def test_protocol_md_status_table_is_generated_from_the_dbc() -> None:
    text = (ROOT / "docs/PROTOCOL.md").read_text()
    shown = dbc_table.region(text, "ESTOP_STATUS")
    assert shown is not None, "docs/PROTOCOL.md lost its generated ESTOP_STATUS table"
    assert shown == dbc_table.table("ESTOP_STATUS"), (
        "docs/PROTOCOL.md's ESTOP_STATUS table differs from the DBC: run "
        "python tools/dbc_table.py --write docs/PROTOCOL.md")


def test_no_other_doc_writes_the_status_layout_out() -> None:
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
            ROOT / "firmware/estopd/README.md"]
    for doc in docs:
        text = doc.read_text()
        if doc.name == "PROTOCOL.md":
            text = text.replace(dbc_table.region(text, "ESTOP_STATUS") or "", "")
        # a byte table of ESTOP_STATUS's counters anywhere else is a second copy
        assert "| 4-5 |" not in text and "valid control packets since the previous" \
            not in text.lower(), doc


def test_the_table_follows_the_dbc(tmp_path: Path) -> None:
    doc = tmp_path / "doc.md"
    doc.write_text(f"x\n{dbc_table.BEGIN.format(name='ESTOP_STATUS')}\nstale\n"
                   f"{dbc_table.END}\ny\n")
    res = subprocess.run([sys.executable, str(ROOT / "tools/dbc_table.py"), "--write",
                          str(doc)], capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 0, res.stderr
    assert dbc_table.region(doc.read_text(), "ESTOP_STATUS") == dbc_table.table()
    assert doc.read_text().startswith("x\n") and doc.read_text().endswith("\ny\n")
    assert "| 3, bits 4-7 | `slowdowns` |" in dbc_table.table()
