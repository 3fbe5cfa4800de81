"""Systematic mutation testing of the firmware core (issue 9).

Every operator site of firmware/core/*.c and of the core's private header (estop_internal.h:
the wire helpers every file inlines) is mutated by class:
  relational   < <= > >= negated, == and != swapped
  boundary     < to <=, <= to <, > to >=, >= to >
  logical      && and || swapped, a ! removed
  arithmetic   + and - swapped, * to /, / and % to *, ++ and -- swapped, += and -= swapped
  bitwise      & | ^ swapped (and their compound assignments), a ~ removed
  shift        << and >> swapped (and <<= >>=)
  constant     an integer literal N to 0, 1, N+1, N-1 (array sizes in declarations excepted)
  statement    an assignment or call statement removed
  return       a return value replaced by 0 and 1 (NULL for pointers)

Each mutant is compiled (gcc -O2) first: a mutant of a .c file into that file's object, a mutant
of the private header into the object of every file that includes it. One that does not compile
is dropped; one whose object code is byte for byte the original's is equivalent by construction
("TCE": the compiler proves it); one whose object code equals an earlier mutant's shares that
mutant's result. The rest are
linked into a cffi module and face the core tests in a process forked from a server that has
already imported pytest and hypothesis: fastest killers first (the deterministic unit tests, the
test that killed most mutants so far first), the property tests with fewer examples, the
stateful model test last at ESTOP_STATEFUL_EXAMPLES. Two mutants run at once (--jobs), each
under a time limit.

A survivor must either be killed by a test or be listed in tools/mutants_equivalent.txt with a
one-line reason; any other survivor fails the run.

  python tools/mutants.py                     every mutant (make mutants)
  python tools/mutants.py --changed HEAD~1    the mutants on lines changed since a revision,
                                              at most --max of them (make test)
  python tools/mutants.py --list              the mutants, not run
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import hashlib
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "firmware" / "core"
sys.path.insert(0, str(ROOT / "pyext"))

# Headers whose code is mutated too: the private header's static inline helpers.
MUTATED_HEADERS = ["estop_internal.h"]
EQUIVALENTS = ROOT / "tools" / "mutants_equivalent.txt"
CACHE = ROOT / "build" / "mutants-cache"
MODULE = "_estop_mutant"
ORIGINAL = "_estop_orig"  # the unmutated build the test server imports the tests against
SWAP_FAILED = 97  # a child's exit status: the mutant's module could not be set up
CFLAGS = ["-O2", "-fPIC", "-fno-strict-aliasing", "-fwrapv", "-std=c99", "-w"]
# Fastest killers first; the stateful model test always last.
TESTS = ["tests/core/test_spec_vectors.py", "tests/core/test_core_rules.py",
         "tests/core/test_core_c_api.py", "tests/core/test_blake2s.py",
         "tests/core/test_core_auth.py", "tests/core/test_core_link_stats.py",
         "tests/core/test_core_mutants.py", "tests/core/test_core_two_stage.py",
         "tests/core/test_core_counters.py", "tests/core/test_core_tag_budget.py",
         "tests/core/test_core_unchecked_replay.py",
         "tests/core/test_core_properties.py", "tests/core/test_core_stateful.py"]
SLOW_TESTS = ("tests/core/test_core_properties.py", "tests/core/test_core_stateful.py")
CLASSES = ["relational", "boundary", "logical", "arithmetic", "bitwise", "shift", "constant",
           "statement", "return"]

TOKEN = re.compile(r"""
    (?P<comment>/\*.*?\*/|//[^\n]*)
  | (?P<pp>^[ \t]*\#(?:[^\n\\]|\\.)*(?:\\\n(?:[^\n\\]|\\.)*)*)
  | (?P<string>"(?:[^"\\\n]|\\.)*"|'(?:[^'\\\n]|\\.)*')
  | (?P<number>\b(?:0[xX][0-9A-Fa-f]+|[0-9]+)[uUlL]*\b)
  | (?P<ident>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<op><<=|>>=|->|\+\+|--|<<|>>|<=|>=|==|!=|&&|\|\||\+=|-=|\*=|/=|%=|&=|\|=|\^=
         |[-+*/%<>=!~&|^?:;,.(){}\[\]])
  | (?P<space>\s+)
""", re.S | re.M | re.X)
DEFINE = re.compile(r"^\s*#\s*define\s+\w+\s+")
KEYWORDS = {"return", "if", "else", "for", "while", "do", "switch", "case", "default", "break",
            "continue", "sizeof", "static", "const", "inline", "typedef", "struct", "enum",
            "goto", "volatile", "extern", "unsigned", "signed"}
TYPES = {"void", "char", "short", "int", "long", "float", "double", "size_t", "uint8_t",
         "uint16_t", "uint32_t", "uint64_t", "int8_t", "int16_t", "int32_t", "int64_t",
         "static", "const", "struct", "enum", "unsigned", "signed", "inline"}
ASSIGN = {"=", "+=", "-=", "*=", "/=", "%=", "&=", "|=", "^=", "<<=", ">>="}


@dataclasses.dataclass
class Tok:
    kind: str
    text: str
    start: int
    line: int
    func: str


@dataclasses.dataclass
class Mutant:
    file: str
    line: int
    func: str
    cls: str
    orig: str
    repl: str
    start: int
    end: int
    key: str = ""
    outcome: str = ""   # invalid, tce, duplicate, killed, timeout, equivalent, survived
    killer: str = ""

    def apply(self, source: str) -> str:
        return source[:self.start] + self.repl + source[self.end:]


def is_type(name: str) -> bool:
    return name in TYPES or name.endswith("_t")


def tokenize(source: str) -> list[Tok]:
    """Code tokens with their line and enclosing function (or table); of preprocessor lines
    only the constants of #define lines without strings (they are sites too)."""
    toks: list[Tok] = []
    depth = 0
    func = ""
    last_ident = ""
    line_starts = [0] + [m.end() for m in re.finditer(r"\n", source)]

    def line_of(pos: int) -> int:
        lo, hi = 0, len(line_starts) - 1
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if line_starts[mid] <= pos:
                lo = mid
            else:
                hi = mid - 1
        return lo + 1

    for m in TOKEN.finditer(source):
        kind = m.lastgroup or ""
        if kind in ("comment", "space", "string"):
            continue
        if kind == "pp":
            d = DEFINE.match(m.group())
            if d and "\\" not in m.group() and '"' not in m.group():
                body = m.group()[d.end():]
                base = m.start() + d.end()
                for n in re.finditer(r"\b(?:0[xX][0-9A-Fa-f]+|[0-9]+)[uUlL]*\b", body):
                    toks.append(Tok("number", n.group(), base + n.start(), line_of(base),
                                    "#define"))
            continue
        text = m.group()
        if depth == 0:
            if kind == "ident":
                last_ident = text if not func else last_ident
            elif text in ("(", "{") and not func:
                func = last_ident
            elif text == ";":
                func = last_ident = ""
        if text == "{":
            depth += 1
        elif text == "}":
            depth -= 1
            if depth == 0:
                func = last_ident = ""
        toks.append(Tok(kind, text, m.start(), line_of(m.start()), func if depth > 0 else ""))
    return toks


def operand_end(tok: Tok | None) -> bool:
    """The token before an operator ends an operand, so the operator is binary."""
    if tok is None:
        return False
    if tok.kind == "number":
        return True
    if tok.kind == "ident":
        return tok.text not in KEYWORDS and not is_type(tok.text)
    return tok.text in (")", "]")


BINARY = {
    "<": [("boundary", "<="), ("relational", ">=")],
    "<=": [("boundary", "<"), ("relational", ">")],
    ">": [("boundary", ">="), ("relational", "<=")],
    ">=": [("boundary", ">"), ("relational", "<")],
    "==": [("relational", "!=")],
    "!=": [("relational", "==")],
    "&&": [("logical", "||")],
    "||": [("logical", "&&")],
    "+": [("arithmetic", "-")],
    "-": [("arithmetic", "+")],
    "*": [("arithmetic", "/")],
    "/": [("arithmetic", "*")],
    "%": [("arithmetic", "*")],
    "&": [("bitwise", "|")],
    "|": [("bitwise", "&")],
    "^": [("bitwise", "|")],
    "<<": [("shift", ">>")],
    ">>": [("shift", "<<")],
    "+=": [("arithmetic", "-=")],
    "-=": [("arithmetic", "+=")],
    "&=": [("bitwise", "|=")],
    "|=": [("bitwise", "&=")],
    "^=": [("bitwise", "|=")],
    "<<=": [("shift", ">>=")],
    ">>=": [("shift", "<<=")],
}


def constant_variants(text: str) -> list[str]:
    m = re.fullmatch(r"(0[xX][0-9A-Fa-f]+|[0-9]+)([uUlL]*)", text)
    if not m:
        return []
    digits, suffix = m.groups()
    value = int(digits, 16) if digits[:2].lower() == "0x" else int(digits)
    fmt = (lambda v: f"0x{v:X}") if digits[:2].lower() == "0x" else str
    out: list[str] = []
    for v in (0, 1, value + 1, value - 1):
        if v >= 0 and v != value and v <= 0xFFFFFFFFFFFFFFFF and fmt(v) + suffix not in out:
            out.append(fmt(v) + suffix)
    return out


def array_dimension(toks: list[Tok], i: int) -> bool:
    """toks[i] is an array's size in a declaration: type [*] name [N] or name [M][N]."""
    j = i - 1
    if j < 0 or toks[j].text != "[":
        return False
    while j >= 1 and toks[j - 1].text == "]":  # an earlier dimension: back to its "["
        j -= 1
        while j >= 0 and toks[j].text != "[":
            j -= 1
    if j < 2 or toks[j - 1].kind != "ident":
        return False
    return is_type(toks[j - 2].text) or toks[j - 2].text == "*"


def statements(toks: list[Tok]) -> Iterator[tuple[int, int]]:
    """(first, semicolon) token indexes of assignment and call statements inside functions."""
    i = 0
    n = len(toks)
    while i < n:
        t = toks[i]
        prev = toks[i - 1].text if i > 0 else ";"
        starts = (t.func and t.func != "#define" and prev in (";", "{", "}")
                  and t.text not in KEYWORDS and t.text not in ("{", "}", ";")
                  and not (t.kind == "ident" and is_type(t.text)))
        if not starts:
            i += 1
            continue
        depth = 0
        j = i
        effect = False
        while j < n and not (toks[j].text == ";" and depth == 0) and depth >= 0:
            s = toks[j].text
            depth += s in ("(", "[", "{")
            depth -= s in (")", "]", "}")
            effect = effect or (depth == 0 and (s in ASSIGN or s in ("++", "--")))
            effect = effect or (toks[j].kind == "ident" and j + 1 < n and toks[j + 1].text == "(")
            j += 1
        if j < n and toks[j].text == ";" and depth == 0:
            decl = t.kind == "ident" and toks[i + 1].kind == "ident"
            if effect and not decl:
                yield i, j
            i = j + 1
        else:
            i += 1


def function_types(toks: list[Tok]) -> dict[str, str]:
    """Return type of each function defined: 'void', 'pointer' or 'value'."""
    out: dict[str, str] = {}
    for i, t in enumerate(toks):
        if t.kind == "ident" and i + 1 < len(toks) and toks[i + 1].text == "(" and not t.func \
                and i > 0 and (is_type(toks[i - 1].text) or toks[i - 1].text == "*"):
            kind = "pointer" if toks[i - 1].text == "*" else (
                "void" if toks[i - 1].text == "void" else "value")
            out.setdefault(t.text, kind)
    return out


def generate(path: Path) -> list[Mutant]:
    source = path.read_text()
    toks = tokenize(source)
    rtypes = function_types(toks)
    name = path.name
    muts: list[Mutant] = []

    def add(tok: Tok, cls: str, repl: str, start: int | None = None, end: int | None = None,
            orig: str | None = None) -> None:
        s = tok.start if start is None else start
        e = tok.start + len(tok.text) if end is None else end
        muts.append(Mutant(name, tok.line, tok.func, cls, orig or tok.text, repl, s, e))

    for i, t in enumerate(toks):
        prev = toks[i - 1] if i > 0 else None
        if t.kind == "number":
            if t.func != "#define" and array_dimension(toks, i):
                continue
            for v in constant_variants(t.text):
                add(t, "constant", v)
            continue
        if t.kind != "op" or not t.func or t.func == "#define":
            continue
        if t.text in BINARY:
            if t.text in ("&", "*", "-", "+") and not operand_end(prev):
                continue  # unary: address-of, dereference, negation
            for cls, repl in BINARY[t.text]:
                add(t, cls, repl)
        elif t.text == "!":
            add(t, "logical", "")
        elif t.text == "~":
            add(t, "bitwise", "")
        elif t.text in ("++", "--"):
            add(t, "arithmetic", "--" if t.text == "++" else "++")
    for i, j in statements(toks):
        t = toks[i]
        text = source[t.start:toks[j].start]
        add(t, "statement", "", t.start, toks[j].start, orig=" ".join(text.split()))
    for i, t in enumerate(toks):
        if t.text != "return" or not t.func:
            continue
        j = i + 1
        depth = 0
        while j < len(toks) and not (toks[j].text == ";" and depth == 0):
            depth += toks[j].text in "([{"
            depth -= toks[j].text in ")]}"
            j += 1
        if j == i + 1:
            continue
        kind = rtypes.get(t.func, "value")
        expr = source[toks[i + 1].start:toks[j].start]
        flat = " ".join(expr.split())
        options = ["NULL"] if kind == "pointer" else (["0", "1"] if kind == "value" else [])
        for v in options:
            if flat.rstrip("uU") != v:
                add(toks[i + 1], "return", v, toks[i + 1].start, toks[j].start, orig=flat)
    # Stable names: file, function, the mutation and which such spot on the line it is.
    lines = source.splitlines()
    seen: collections.Counter[str] = collections.Counter()
    for m in sorted(muts, key=lambda m: (m.start, m.cls, m.repl)):
        text = " ".join(lines[m.line - 1].split())
        base = f"{m.file}:{m.func or '-'}: {m.cls} '{m.orig}' -> '{m.repl}' in `{text}`"
        seen[base] += 1
        m.key = base if seen[base] == 1 else f"{base} #{seen[base]}"
    muts.sort(key=lambda m: (m.file, m.start, m.cls, m.repl))
    return muts


def mutated_files() -> list[Path]:
    return sorted(CORE.glob("*.c")) + [CORE / h for h in MUTATED_HEADERS if (CORE / h).exists()]


def dependents(name: str) -> list[str]:
    """The .c files whose object a mutant of this file changes: itself, or for a header every
    core source that includes it."""
    if name.endswith(".c"):
        return [name]
    return [f.name for f in sorted(CORE.glob("*.c")) if f'#include "{name}"' in f.read_text()]


def all_mutants() -> list[Mutant]:
    return [m for p in mutated_files() for m in generate(p)]


def load_equivalents() -> dict[str, str]:
    out: dict[str, str] = {}
    if EQUIVALENTS.exists():
        for raw in EQUIVALENTS.read_text().splitlines():
            if not raw.strip() or raw.startswith("#"):
                continue
            # The name ends at the backtick closing the line's text (code has no backticks).
            m = re.match(r"^(.*? in `[^`]*`(?: #\d+)?) \| (.+)$", raw)
            if not m or not m.group(2).strip():
                raise SystemExit(f"mutants: error: {EQUIVALENTS.name}: no reason: {raw}")
            out[m.group(1)] = m.group(2).strip()
    return out


def changed_lines(rev: str) -> dict[str, set[int]] | None:
    """Lines of firmware/core/*.c (and the mutated headers) added or changed since rev; None
    when rev is unknown."""
    ok = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                        cwd=ROOT, capture_output=True)
    if ok.returncode != 0:
        return None
    diff = subprocess.run(["git", "diff", "-U0", rev, "--", "firmware/core/"], cwd=ROOT,
                          capture_output=True, text=True, check=True).stdout
    out: dict[str, set[int]] = collections.defaultdict(set)
    current = ""
    for line in diff.splitlines():
        if line.startswith("+++ "):
            current = Path(line[4:]).name if line[4:] != "/dev/null" else ""
        m = re.match(r"@@ -\S+ \+(\d+)(?:,(\d+))? @@", line)
        if m and (current.endswith(".c") or current in MUTATED_HEADERS):
            first, count = int(m.group(1)), int(m.group(2) or "1")
            out[current].update(range(first, first + count))
    return out


# ---- building --------------------------------------------------------------------------------

class Builder:
    """Objects of the original sources, the cffi wrapper, and mutant objects by hash."""

    def __init__(self, work: Path) -> None:
        from build_core import make_builder

        self.work = work
        self.base = work / "base"
        self.base.mkdir(parents=True)
        for f in CORE.iterdir():
            shutil.copy(f, self.base / f.name)
        include = sysconfig.get_paths()["include"]
        self.suffix = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
        for module in (MODULE, ORIGINAL):
            wrapper = self.base / f"{module}.c"
            make_builder(module, relative=False, core_dir=self.base).emit_c_code(str(wrapper))
            self.cc(wrapper, self.base / f"{module}.o", [f"-I{include}", f"-I{self.base}"])
        self.objs: dict[str, Path] = {}
        self.hashes: dict[str, str] = {}
        for f in sorted(CORE.glob("*.c")):
            obj = self.base / (f.stem + ".o")
            self.cc(self.base / f.name, obj, [])
            self.objs[f.name] = obj
            self.hashes[f.name] = digest(obj)
        self.link(self.objs, work / "orig", ORIGINAL)

    def original_hash(self, name: str) -> str:
        """The object code a mutant of this file is compared with (all its dependents)."""
        return combined({f: self.hashes[f] for f in dependents(name)})

    def cc(self, src: Path, obj: Path, extra: list[str]) -> bool:
        r = subprocess.run(["gcc", *CFLAGS, *extra, "-c", src.name, "-o", str(obj)],
                           cwd=src.parent, capture_output=True)
        return r.returncode == 0

    def link(self, objs: dict[str, Path], outdir: Path, module: str = MODULE) -> None:
        outdir.mkdir(parents=True, exist_ok=True)
        subprocess.run(["gcc", "-shared", "-o", str(outdir / (module + self.suffix)),
                        str(self.base / f"{module}.o"), *map(str, objs.values())], check=True)


def digest(obj: Path) -> str:
    return hashlib.sha256(obj.read_bytes()).hexdigest()


def combined(hashes: dict[str, str]) -> str:
    """One hash for the objects of several files (a header mutant changes them all)."""
    return hashlib.sha256(" ".join(f"{k}={v}" for k, v in sorted(hashes.items())).encode()
                          ).hexdigest()


def mutant_obj(work: Path, index: int, cfile: str) -> Path:
    return work / "obj" / f"{index}.{Path(cfile).stem}.o"


def source_key(cfile: str, sources: dict[str, str]) -> str:
    """Names an object in the cache: the file compiled, every source and header it may see
    (a mutant's text in place of its file), and the flags."""
    h = hashlib.sha256(" ".join(CFLAGS).encode() + cfile.encode())
    for name in sorted(sources):
        h.update(name.encode() + b"\0" + sources[name].encode() + b"\0")
    return h.hexdigest()


def compile_all(builder: Builder, muts: list[Mutant], jobs: int) -> dict[int, str]:
    """Object hashes of the mutants that compile (two gcc at a time). A mutant of a .c file
    compiles that file; a mutant of a header compiles every file that includes it (its hash
    covers them all). Objects are kept in build/mutants-cache/ by source, so a run after a
    test-only change compiles nothing."""
    CACHE.mkdir(parents=True, exist_ok=True)
    (builder.work / "obj").mkdir(exist_ok=True)
    originals = {f.name: f.read_text() for f in CORE.iterdir()
                 if f.suffix in (".c", ".h")}
    headers = {n: s for n, s in originals.items() if n.endswith(".h")}
    # (mutant index, file to compile, the sources it sees, cache key)
    todo: list[tuple[int, str, dict[str, str], str]] = []
    parts: dict[int, dict[str, str]] = {}   # index -> compiled file -> object hash
    failed: set[int] = set()
    for index, m in enumerate(muts):
        text = m.apply(originals[m.file])
        parts[index] = {}
        for cfile in dependents(m.file):
            seen = dict(headers)
            seen[cfile] = originals[cfile]
            seen[m.file] = text
            key = source_key(cfile, seen)
            cached = CACHE / f"{key}.o"
            obj = mutant_obj(builder.work, index, cfile)
            if cached.exists():
                shutil.copy(cached, obj)
                parts[index][cfile] = digest(obj)
            elif (CACHE / f"{key}.invalid").exists():
                failed.add(index)
            else:
                todo.append((index, cfile, seen, key))
    running: dict[subprocess.Popen[bytes], tuple[int, str, Path, Path, str]] = {}
    serial = 0
    while todo or running:
        while todo and len(running) < jobs:
            index, cfile, seen, key = todo.pop(0)
            serial += 1
            d = builder.work / "src" / str(serial)
            d.mkdir(parents=True)
            for name in seen:
                if name == cfile or seen[name] != originals.get(name):
                    (d / name).write_text(seen[name])
                else:
                    (d / name).symlink_to(builder.base / name)
            obj = mutant_obj(builder.work, index, cfile)
            p = subprocess.Popen(["gcc", *CFLAGS, "-c", cfile, "-o", str(obj)], cwd=d,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            running[p] = (index, cfile, d, obj, key)
        for p in list(running):
            if p.poll() is not None:
                index, cfile, d, obj, key = running.pop(p)
                if p.returncode == 0:
                    parts[index][cfile] = digest(obj)
                    shutil.copy(obj, CACHE / f"{key}.o")
                else:
                    failed.add(index)
                    (CACHE / f"{key}.invalid").touch()
                shutil.rmtree(d)
        time.sleep(0.005)
    return {index: combined(hashes) for index, hashes in parts.items()
            if index not in failed and len(hashes) == len(dependents(muts[index].file))}


# ---- running the tests in forked children ------------------------------------------------------

class Runner:
    def __init__(self, builder: Builder, examples: int, cap: int) -> None:
        self.builder = builder
        self.examples = examples
        self.cap = cap
        # Kills by (mutated file, test): a test that kills a file's mutants runs first on it.
        self.kills: collections.Counter[tuple[str, str]] = collections.Counter()
        # Imported once here, so every forked child starts with them loaded.
        import hypothesis
        import pytest  # noqa: F401

        original = hypothesis.settings.__init__
        cap_examples = cap

        def capped(self_: object, parent: object = None, **kw: object) -> None:
            if "max_examples" in kw:
                kw["max_examples"] = min(int(kw["max_examples"]), cap_examples)  # type: ignore[call-overload]
            original(self_, parent, **kw)  # type: ignore[arg-type]

        hypothesis.settings.__init__ = capped  # type: ignore[assignment,method-assign]
        # No shrinking: a failing example kills the mutant as it is (shrinking would rerun
        # the test many times for nothing).
        hypothesis.settings.register_profile(
            "mutants", derandomize=True, database=None, deadline=None, print_blob=False,
            phases=(hypothesis.Phase.explicit, hypothesis.Phase.generate),
            report_multiple_bugs=False)
        hypothesis.settings.load_profile("mutants")
        # The tests are imported once, here, against the unmutated build; each child swaps in
        # its mutant's lib and ffi (the tests hold no cdata at module level). The baseline run
        # checks that the swap works: the tests must pass on the original through it.
        os.environ["ESTOP_CORE_MODULE"] = ORIGINAL
        os.environ["ESTOP_STATEFUL_EXAMPLES"] = str(examples)
        sys.path.insert(0, str(builder.work / "orig"))
        sys.path.insert(0, str(ROOT / "tests"))
        # Each test imported by its module name from its own directory (tests/core/...): with
        # tests/ alone on the path, none was found once the tests moved into tests/core.
        for folder in sorted({str((ROOT / t).parent) for t in TESTS}):
            sys.path.insert(0, folder)
        import importlib

        for test in TESTS:
            if (ROOT / test).exists():
                importlib.import_module(Path(test).stem)

    def start(self, objs: dict[str, Path], outdir: Path, file: str = "",
              cpu_limit: int = 0) -> int:
        """Forks a child that links the module into outdir and runs the tests against it."""
        pid = os.fork()
        if pid != 0:
            try:
                os.setpgid(pid, pid)  # also in the child: whoever runs first
            except OSError:
                pass
        if pid == 0:  # the child
            code = SWAP_FAILED  # any failure to set the mutant up is the tool's, not a kill
            try:
                if cpu_limit > 0:
                    # CPU seconds, not wall time: a loaded machine does not turn a slow
                    # survivor into a "timeout"; a mutant that loops gets SIGXCPU.
                    resource.setrlimit(resource.RLIMIT_CPU, (cpu_limit, cpu_limit + 5))
                self.builder.link(objs, outdir)
                code = self.child(outdir, file)
            finally:
                os._exit(code)
        return pid

    def child(self, outdir: Path, file: str) -> int:
        import pytest

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        os.setpgid(0, 0)
        sys.path.insert(0, str(outdir))
        import importlib

        try:
            new = importlib.import_module(MODULE)
        except ImportError:
            return SWAP_FAILED
        old = sys.modules[ORIGINAL]
        olds = (old, old.lib, old.ffi)  # type: ignore[attr-defined]
        swap = {id(old): new, id(old.lib): new.lib, id(old.ffi): new.ffi}  # type: ignore[attr-defined]
        for mod in list(sys.modules.values()):
            for name, value in list(getattr(mod, "__dict__", {}).items()):
                if id(value) in swap and any(value is x for x in olds):
                    setattr(mod, name, swap[id(value)])
        os.environ["ESTOP_CORE_MODULE"] = MODULE
        if sys.modules["estop.core"].lib is not new.lib:  # type: ignore[attr-defined]
            return SWAP_FAILED
        kills = self.kills
        result = outdir / "killer"

        class Order:
            """Slow tests last, then the tests that killed most so far first."""

            def pytest_collection_modifyitems(self, items: list[pytest.Item]) -> None:
                def key(item: pytest.Item) -> tuple[int, int, int]:
                    slow = SLOW_TESTS.index(item.nodeid.split("::")[0]) + 1 \
                        if item.nodeid.split("::")[0] in SLOW_TESTS else 0
                    return (slow, -kills[(file, item.nodeid)], 0)
                items.sort(key=key)

            def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
                if report.failed and not result.exists():
                    result.write_text(report.nodeid)

        tests = [t for t in TESTS if (ROOT / t).exists()]
        rc = pytest.main(["-q", "-x", "-p", "no:cacheprovider", "-p", "no:randomly",
                          "-o", "addopts=", *tests], plugins=[Order()])
        return int(rc)


def run(args: argparse.Namespace) -> int:
    muts = all_mutants()
    equivalents = load_equivalents()
    scope = "every mutant"
    if args.changed:
        lines = changed_lines(args.changed)
        if lines is None:
            print(f"mutants: no revision {args.changed!r} to compare with: nothing to run")
            return 0
        muts = [m for m in muts if m.line in lines.get(m.file, set())]
        scope = f"the mutants on lines of firmware/core/*.c changed since {args.changed}"
        if len(muts) > args.max:
            step = len(muts) / args.max
            picked = [muts[int(i * step)] for i in range(args.max)]
            print(f"mutants: {len(muts)} mutants on the changed lines, over the cap of {args.max}"
                  f" for this run: running an even sample of {args.max}; `make mutants` runs all")
            muts = picked
    if args.only:
        muts = [m for m in muts if args.only in m.key]
    if args.keys:
        wanted = {k.strip() for k in Path(args.keys).read_text().splitlines() if k.strip()}
        muts = [m for m in muts if m.key in wanted]
    if args.cls:
        muts = [m for m in muts if m.cls in args.cls.split(",")]
    if args.list:
        for m in muts:
            print(f"{m.line:4d} {m.key}")
        print(f"{len(muts)} mutants")
        return 0
    if not muts:
        print(f"mutants: none in scope ({scope})")
        return 0
    t0 = time.monotonic()
    work = Path(tempfile.mkdtemp(prefix="mutants-", dir=ROOT / "build")) \
        if (ROOT / "build").is_dir() else Path(tempfile.mkdtemp(prefix="mutants-"))
    try:
        return campaign(args, muts, equivalents, work, scope, t0)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def campaign(args: argparse.Namespace, muts: list[Mutant], equivalents: dict[str, str],
             work: Path, scope: str, t0: float) -> int:
    builder = Builder(work)
    hashes = compile_all(builder, muts, args.jobs)
    first_of: dict[tuple[str, str], int] = {}
    to_run: list[int] = []
    for i, m in enumerate(muts):
        h = hashes.get(i)
        if h is None:
            m.outcome = "invalid"
        elif h == builder.original_hash(m.file):
            m.outcome = "tce"
        elif (m.file, h) in first_of:
            m.outcome = "duplicate"
        else:
            first_of[(m.file, h)] = i
            to_run.append(i)
    compile_time = time.monotonic() - t0
    runner = Runner(builder, args.examples, args.max_examples)
    limit = args.wall_limit
    cpu_limit = args.cpu_limit
    baseline_note = "not run (make coverage runs the suite)"
    if not args.changed and to_run:
        # The unmutated core first: it must pass, and its CPU time sets the limit per mutant.
        t1 = time.monotonic()
        pid = runner.start(dict(builder.objs), work / "run" / "original")
        _, status, usage = os.wait4(pid, 0)
        baseline = time.monotonic() - t1
        if os.waitstatus_to_exitcode(status) != 0:
            print("mutants: error: the core tests fail on the unmutated core", file=sys.stderr)
            return 2
        cpu = usage.ru_utime + usage.ru_stime
        cpu_limit = max(cpu_limit, int(4 * cpu) + 1)
        baseline_note = f"passes in {baseline:.1f} s ({cpu:.1f} s CPU)"
    print(f"mutants: {scope}: {len(muts)} mutants, {len(to_run)} to test after compiling "
          f"({compile_time:.0f} s); the unmutated core {baseline_note}; limit {cpu_limit} s "
          f"CPU ({limit:.0f} s wall) a mutant, {args.jobs} at a time", flush=True)
    running: dict[int, tuple[int, float, Path]] = {}
    queue = list(to_run)
    done = 0
    while queue or running:
        while queue and len(running) < args.jobs:
            i = queue.pop(0)
            m = muts[i]
            objs = dict(builder.objs)
            for cfile in dependents(m.file):
                objs[cfile] = mutant_obj(work, i, cfile)
            outdir = work / "run" / str(i)
            pid = runner.start(objs, outdir, m.file, cpu_limit)
            running[pid] = (i, time.monotonic(), outdir)
        pid, status = os.waitpid(-1, os.WNOHANG)
        if pid == 0:
            now = time.monotonic()
            for p, (i, started, _) in list(running.items()):
                if now - started > limit:
                    try:
                        os.killpg(p, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    muts[i].outcome = "timeout"
            time.sleep(0.02)
            continue
        if pid not in running:
            continue
        i, _, outdir = running.pop(pid)
        m = muts[i]
        code = os.waitstatus_to_exitcode(status)
        if os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGXCPU:
            m.outcome = "timeout"
        if code == SWAP_FAILED:
            print(f"mutants: error: could not set up the module of {m.key}", file=sys.stderr)
            return 2
        if m.outcome != "timeout":
            if code == 0:
                m.outcome = "equivalent" if m.key in equivalents else "survived"
            else:
                m.outcome = "killed"
                killer = outdir / "killer"
                m.killer = killer.read_text() if killer.exists() else f"exit {code}"
                runner.kills[(m.file, m.killer)] += 1
        shutil.rmtree(outdir, ignore_errors=True)
        done += 1
        if m.outcome == "survived" or args.verbose:
            print(f"  {m.outcome:10s} {m.key}" + (f"  [{m.killer}]" if m.killer else ""),
                  flush=True)
        elif done % 100 == 0:
            print(f"  ... {done}/{len(to_run)} tested, {time.monotonic() - t0:.0f} s", flush=True)
    # Duplicates share the result of the first mutant with the same object code.
    for i, m in enumerate(muts):
        if m.outcome == "duplicate":
            h = hashes[i]
            first = muts[first_of[(m.file, h)]]
            if first.outcome in ("killed", "timeout"):
                m.outcome = first.outcome
            else:
                m.outcome = "equivalent" if m.key in equivalents else "survived"
                if m.outcome == "survived":
                    print(f"  survived   {m.key}  (same object code as: {first.key})")
    return report(args, muts, equivalents, time.monotonic() - t0)


def report(args: argparse.Namespace, muts: list[Mutant], equivalents: dict[str, str],
           elapsed: float) -> int:
    cols = ["mutants", "invalid", "tce", "killed", "timeout", "equivalent", "survived"]
    table: dict[str, collections.Counter[str]] = {c: collections.Counter() for c in CLASSES}
    sites: dict[str, set[tuple[str, int]]] = {c: set() for c in CLASSES}
    for m in muts:
        table[m.cls]["mutants"] += 1
        table[m.cls][m.outcome] += 1
        sites[m.cls].add((m.file, m.start))
    print()
    print("class        sites  " + "  ".join(f"{c:>10s}" for c in cols))
    total: collections.Counter[str] = collections.Counter()
    all_sites = 0
    for c in CLASSES:
        if table[c]["mutants"] == 0:
            continue
        total.update(table[c])
        all_sites += len(sites[c])
        print(f"{c:12s} {len(sites[c]):5d}  " + "  ".join(f"{table[c][k]:10d}" for k in cols))
    print(f"{'total':12s} {all_sites:5d}  " + "  ".join(f"{total[k]:10d}" for k in cols))
    print("(invalid: does not compile; tce: the same object code as the original, equivalent by "
          "construction;\n equivalent: survives and is listed with its reason in "
          f"{EQUIVALENTS.relative_to(ROOT)}; timeout: killed by the time limit)")
    print(f"mutants: {elapsed:.0f} s")
    rc = 0
    survivors = [m for m in muts if m.outcome == "survived"]
    if survivors:
        print(f"mutants: {len(survivors)} unexplained survivors (a test must kill each, or "
              f"{EQUIVALENTS.name} must say why it is equivalent):")
        for m in survivors:
            print(f"  {m.key}")
        rc = 1
    wrong = [m for m in muts if m.key in equivalents and m.outcome in ("killed", "timeout")]
    for m in wrong:
        print(f"mutants: listed as equivalent but killed (remove it from {EQUIVALENTS.name}): "
              f"{m.key}")
        rc = 1
    if not args.changed and not args.only and not args.cls and not args.keys:
        keys = {m.key for m in muts}
        for k in equivalents:
            if k not in keys:
                print(f"mutants: {EQUIVALENTS.name} lists a mutant that no longer exists: {k}")
                rc = 1
    return rc


def main() -> int:
    parser = argparse.ArgumentParser(description="systematic mutation testing of the core")
    parser.add_argument("--changed", metavar="REV", help="only lines changed since REV")
    parser.add_argument("--max", type=int, default=40,
                        help="with --changed: at most this many mutants (default 40)")
    parser.add_argument("--jobs", type=int, default=2, help="mutants at once (default 2)")
    parser.add_argument("--examples", type=int, default=60,
                        help="stateful examples a mutant (default 60)")
    parser.add_argument("--max-examples", type=int, default=100,
                        help="cap on any other hypothesis test's examples (default 100)")
    parser.add_argument("--cpu-limit", type=int, default=20,
                        help="least CPU seconds a mutant (default 20; 4 times the unmutated "
                             "run's when that is more)")
    parser.add_argument("--wall-limit", type=float, default=300.0,
                        help="wall-clock seconds a mutant, a backstop (default 300)")
    parser.add_argument("--only", default="", help="mutants whose name contains this")
    parser.add_argument("--cls", default="", help="comma-separated operator classes")
    parser.add_argument("--keys", default="", help="a file of mutant names, one a line: only "
                        "those (e.g. the survivors of a run, once tests are added)")
    parser.add_argument("--list", action="store_true", help="list the mutants, run none")
    parser.add_argument("--verbose", action="store_true", help="one line a mutant")
    args = parser.parse_args()
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
