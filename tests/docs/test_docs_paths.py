"""The docs say what is there: every repository path they name exists (issue 17), and the
daemon README's start line and event list are estopd's own.

Paths: every `dir/...` token whose first part is a top-level directory of the repository, and
every relative Markdown link, in the Markdown files and the deploy/ files. Paths of things the
build makes (build/, firmware/build/, hil/out/, bench/out/, .venv/) are left out, and a name
ending in `_` or `-` is a prefix (`tests/mcu/test_mcu_` stands for tests/mcu/test_mcu_*)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

GENERATED = ("build/", "firmware/build/", "hil/out/", "bench/out/", ".venv/")


def _tracked(pattern: str) -> list[Path]:
    res = subprocess.run(["git", "ls-files", "--", pattern], cwd=ROOT, capture_output=True,
                         text=True, timeout=30, check=True)
    return [ROOT / line for line in res.stdout.splitlines()]


def _docs() -> list[Path]:
    docs = [p for p in _tracked("*.md") if p.exists()]
    return docs + [p for p in _tracked("deploy/*") if p.exists()]


def _named_paths(doc: Path) -> list[tuple[int, str]]:
    tops = "|".join(re.escape(p.name) for p in ROOT.iterdir()
                    if p.is_dir() and not p.name.startswith("."))
    token = re.compile(rf"(?<![\w./-])((?:{tops})/[\w./-]*)")
    link = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
    found: list[tuple[int, str]] = []
    for no, line in enumerate(doc.read_text().splitlines(), 1):
        found += [(no, m.group(1).rstrip(".")) for m in token.finditer(line)]
        found += [(no, str((doc.parent / m.group(1)).relative_to(ROOT)))
                  for m in link.finditer(line)
                  if "://" not in m.group(1) and not m.group(1).startswith("/")]
    return found


def _exists(path: str) -> bool:
    if path.startswith(GENERATED):
        return True
    if path.endswith(("_", "-")):
        return any(ROOT.glob(path + "*"))
    return (ROOT / path).exists()


def test_every_path_the_docs_name_exists() -> None:
    missing = [f"{doc.relative_to(ROOT)}:{no}: {path}" for doc in _docs()
               for no, path in _named_paths(doc) if not _exists(path)]
    assert not missing, "paths named in the docs that do not exist:\n" + "\n".join(missing)


def test_the_path_check_finds_a_missing_path(tmp_path: Path) -> None:
    doc = ROOT / "docs" / "REMOTE.md"
    named = dict((p, n) for n, p in _named_paths(doc))
    assert "src/estop/client/sender.py" in named
    assert not _exists("deploy/estopd.service") and not _exists("fuzz/regression/")
    assert _exists("tests/mcu/test_mcu_") and _exists("build/fuzz/fuzz_core")


# -- the daemon README -------------------------------------------------------------------------

README = ROOT / "firmware" / "estopd" / "README.md"


def _section(title: str) -> str:
    text = README.read_text()
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 3)
    return text[start:end if end > 0 else None]


def test_readme_start_line_has_the_keys_of_a_real_start_line(tmp_path: Path, estopd: str) -> None:
    key = tmp_path / "key"
    key.write_text("00" * 32 + "\n")
    key.chmod(0o600)
    proc = subprocess.Popen([estopd, "--key-file", str(key), "--udp-port", "0",
                             "--tcp-port", "0", "--bind", "127.0.0.1",
                             "--can-log", str(tmp_path / "can.log")],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        real = proc.stderr.readline()
    finally:
        proc.kill()
        proc.wait(timeout=10)
    shown = next(line.strip() for line in _section("Start line").splitlines()
                 if line.strip().startswith("estopd <t_mono> start"))
    keys = re.findall(r"(\w+)=", real)
    assert re.match(r"estopd \d+\.\d+ start ", real), real
    assert re.findall(r"(\w+)=", shown) == keys, (shown, real)


def test_readme_lists_every_event_estopd_logs() -> None:
    names: set[str] = set()
    for src in sorted((ROOT / "firmware" / "estopd").glob("*.c")):
        text = src.read_text()
        for m in re.finditer(r"\b(log_event|log_limited|log_client|emit)\s*\(([^;]*?)\)\s*;",
                             text, re.S):
            literal = re.search(r'"([a-z_]+)"', m.group(2))
            if literal:
                names.add(literal.group(1))
    assert {"start", "state", "exit", "link_histogram", "can_error"} <= names  # the scan works
    listed = set(re.findall(r"`([a-z_]+)[` ]", _section("Events")))
    assert names - listed == set(), f"events estopd logs that its README does not list: " \
                                    f"{sorted(names - listed)}"


@pytest.mark.parametrize("path", ["README.md", "docs/DEPLOY.md"])
def test_no_doc_tells_a_team_to_copy_the_root_only_key_directly(path: str) -> None:
    text = (ROOT / path).read_text()
    assert "scp /etc/estop/key" not in text
