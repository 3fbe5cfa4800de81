"""The MISRA C:2012 gate of the firmware core (make check).

1. Self-test: cppcheck's misra addon runs on tests/misra/planted.c, whose lines marked
   "planted: R" break rule R. Every one must be reported; otherwise the checker is missing,
   broken or silenced, and the gate fails rather than pass on silence.
2. The check: cppcheck (its own style, warning, portability and performance checks, and the
   misra addon, rule numbers only: the rule texts are licensed and not needed) on
   firmware/core/*.c and the headers they include. Every finding must match a deviation of
   firmware/core/misra-deviations.txt (same rule, same file, and the deviation's symbol on the
   finding's line, so a deviation follows its code when lines move); every deviation must match
   a finding (a stale one fails too, so the file stays true).
Prints the findings it fails on, one a line; exit status 0 when clean.
"""

from __future__ import annotations

import dataclasses
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "firmware" / "core"
DEVIATIONS = CORE / "misra-deviations.txt"
PLANTED = ROOT / "tests" / "misra" / "planted.c"
BUILD = ROOT / "build" / "misra"
TEMPLATE = "{file}\t{line}\t{id}\t{severity}\t{message}"


@dataclasses.dataclass(frozen=True)
class Finding:
    file: str
    line: int
    rule: str
    message: str

    def text(self) -> str:
        return f"{self.file}:{self.line}: {self.rule}: {self.message}"


@dataclasses.dataclass
class Deviation:
    rule: str
    file: str
    symbol: str
    why: str
    used: int = 0


def run_cppcheck(files: list[Path], build_dir: Path | None) -> list[Finding]:
    if shutil.which("cppcheck") is None:
        raise SystemExit("misra: error: cppcheck is not installed (scripts/ensure-debs check)")
    cmd = ["cppcheck", "--addon=misra", "--std=c99", "--enable=style,warning,portability,"
           "performance", "--inline-suppr", "--suppress=missingIncludeSystem", "-q",
           f"-I{CORE}", f"--template={TEMPLATE}"]
    if build_dir is not None:
        build_dir.mkdir(parents=True, exist_ok=True)
        cmd.append(f"--cppcheck-build-dir={build_dir}")
    proc = subprocess.run([*cmd, *map(str, files)], capture_output=True, text=True, cwd=ROOT)
    out = proc.stdout + proc.stderr
    if proc.returncode != 0 or re.search(r"Failed to execute|Bailing out|addon.*(error|fail)",
                                         out, re.I):
        raise SystemExit(f"misra: error: cppcheck failed (exit {proc.returncode}):\n{out}")
    findings = []
    for line in out.splitlines():
        parts = line.split("\t")
        if len(parts) != 5:
            raise SystemExit(f"misra: error: cppcheck printed an unexpected line: {line}")
        path, lineno, rule, _severity, message = parts
        rule = rule.removeprefix("misra-c2012-")
        rel = Path(path).resolve().relative_to(ROOT) if Path(path).is_absolute() else Path(path)
        findings.append(Finding(str(rel), int(lineno), rule, message))
    return findings


def self_test() -> None:
    expected = {(n, m.group(1)) for n, text in enumerate(PLANTED.read_text().splitlines(), 1)
                for m in [re.search(r"planted: (\d+\.\d+)", text)] if m}
    if len(expected) < 5:
        raise SystemExit(f"misra: error: {PLANTED.name} plants too few violations")
    got = {(f.line, f.rule) for f in run_cppcheck([PLANTED], None)}
    missed = sorted(expected - got)
    if missed:
        raise SystemExit("misra: error: the checker missed planted violations (line, rule): "
                         f"{missed}; is cppcheck's misra addon working?")


def load_deviations() -> list[Deviation]:
    devs = []
    for n, raw in enumerate(DEVIATIONS.read_text().splitlines(), 1):
        if not raw.strip() or raw.lstrip().startswith("#"):
            continue
        parts = [p.strip() for p in raw.split("|", 3)]
        if len(parts) != 4 or not all(parts):
            raise SystemExit(f"misra: error: {DEVIATIONS.name}:{n}: want 'rule | file | symbol "
                             "| why', got: {raw}")
        devs.append(Deviation(*parts))
    return devs


def main() -> int:
    self_test()
    devs = load_deviations()
    # A fresh build directory every run: cppcheck's incremental results are kept per .c file and
    # went stale when only the private header changed (a merge produced 13 false findings).
    shutil.rmtree(BUILD, ignore_errors=True)
    findings = run_cppcheck(sorted(CORE.glob("*.c")), BUILD)
    bad = []
    for f in findings:
        source = (ROOT / f.file).read_text().splitlines()
        text = source[f.line - 1] if 0 < f.line <= len(source) else ""
        match = [d for d in devs if d.rule == f.rule and Path(f.file).name == d.file
                 and d.symbol in text]
        if match:
            match[0].used += 1
        else:
            bad.append(f)
    for f in bad:
        print(f"misra: finding without a deviation: {f.text()}")
    stale = [d for d in devs if d.used == 0]
    for d in stale:
        print(f"misra: deviation matches no finding (remove it): {d.rule} {d.file} {d.symbol}")
    if bad or stale:
        return 1
    print(f"misra: firmware/core clean: {len(findings)} findings, each a recorded deviation "
          f"({len(devs)} in {DEVIATIONS.relative_to(ROOT)}); self-test found every planted "
          "violation")
    return 0


if __name__ == "__main__":
    sys.exit(main())
