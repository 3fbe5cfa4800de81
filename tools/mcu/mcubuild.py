"""The core built for Cortex-M: build, symbol check, footprint, stack bound, struct layout.

Everything here is read from the build itself, never written down by hand, so that the checks
follow the core as it grows: the sources are every ``firmware/core/*.c`` (firmware/mcu/Makefile
uses a wildcard), the entry points are the prototypes of the core's headers, sizes come from the
linked ELF, struct layouts from its DWARF, frames from gcc's ``.su``/``.ci`` files.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from elftools.elf.elffile import ELFFile

ROOT = Path(__file__).resolve().parents[2]
CORE_DIR = Path(os.environ.get("ESTOP_MCU_CORE", ROOT / "firmware" / "core"))
OUT_DIR = Path(os.environ.get("ESTOP_MCU_OUT", ROOT / "build" / "mcu"))
MAKEFILE_DIR = ROOT / "firmware" / "mcu"
TOOL_PREFIX = "arm-none-eabi-"
TARGETS = ("m0plus", "m4")
LEVELS = ("Os", "O2")
CPU_FLAGS = {
    "m0plus": ["-mcpu=cortex-m0plus", "-mthumb", "-mfloat-abi=soft"],
    "m4": ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=soft"],
}
TARGET_NAMES = {"m0plus": "Cortex-M0+", "m4": "Cortex-M4"}

# The footprint budget of issue 10.
BUDGET_FLASH = 8 * 1024      # text + rodata of the whole core, M0+ at -Os
BUDGET_STATE = 1024          # sizeof(estop_core_t)
BUDGET_STACK = 512           # worst-case stack of any entry point, M0+ ...
BUDGET_STACK_VARIANTS = ("m0plus-Os",)   # ... at -Os, the build the flash budget names too


class McuError(Exception):
    """The MCU build cannot be made or breaks one of its rules (one line for users)."""


@dataclass(frozen=True)
class Variant:
    target: str   # m0plus | m4
    level: str    # Os | O2
    out: Path = OUT_DIR
    core: Path = CORE_DIR

    @property
    def name(self) -> str:
        return f"{self.target}-{self.level}"

    @property
    def dir(self) -> Path:
        return self.out / self.name

    @property
    def elf(self) -> Path:
        return self.dir / "core.elf"

    @property
    def label(self) -> str:
        return f"{TARGET_NAMES[self.target]} -{self.level}"

    def objects(self) -> list[Path]:
        return [self.dir / f"{src.stem}.o" for src in core_sources(self.core)]


VARIANTS = tuple(Variant(t, lv) for t in TARGETS for lv in LEVELS)


def variant(name: str) -> Variant:
    for v in VARIANTS:
        if v.name == name:
            return v
    raise McuError(f"no MCU variant {name!r} (have {', '.join(v.name for v in VARIANTS)})")


def core_sources(core: Path = CORE_DIR) -> list[Path]:
    return sorted(core.glob("*.c"))


def core_headers(core: Path = CORE_DIR) -> list[Path]:
    return sorted(core.glob("*.h"))


# The core's private header (wire helpers, the estop__* functions its files share): no entry
# points there.
PRIVATE_HEADERS = ("estop_internal.h",)


def public_headers(core: Path = CORE_DIR) -> list[Path]:
    return [h for h in core_headers(core) if h.name not in PRIVATE_HEADERS]


# ---- toolchain and build -------------------------------------------------------------------

def tool(name: str) -> str:
    path = shutil.which(TOOL_PREFIX + name)
    if path is None:
        raise McuError(
            f"{TOOL_PREFIX}{name} not found: the Cortex-M toolchain is missing "
            "(scripts/ensure-debs mcu installs it; make mcu and make test run that)")
    return path


def run(cmd: list[str], cwd: Path | None = None) -> str:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise McuError(f"{Path(cmd[0]).name} failed:\n{proc.stdout}{proc.stderr}".rstrip())
    return proc.stdout


def make(target: str, core: Path = CORE_DIR, out: Path = OUT_DIR,
         variants: Iterable[Variant] = ()) -> None:
    tool("gcc")
    names = " ".join(v.name for v in variants)
    run(["make", "--no-print-directory", "-s", "-j2", "-C", str(MAKEFILE_DIR), target,
         f"CORE={core}", f"OUT={out}", *([f"VARIANTS={names}"] if names else [])])


def build(core: Path = CORE_DIR, out: Path = OUT_DIR,
          names: Iterable[str] = ()) -> list[Variant]:
    """Compiles the variants (all by default), checks the symbols the objects need, then
    links. Returns the variants built."""
    chosen = [Variant(t, lv, out, core) for t in TARGETS for lv in LEVELS
              if not names or f"{t}-{lv}" in names]
    make("objects", core, out, chosen)
    problems = [p for v in chosen for p in foreign_symbols(v)]
    if problems:
        raise McuError("the core needs symbols that neither the core nor libgcc defines "
                       "(nothing of libc is linked):\n  " + "\n  ".join(problems))
    make("all", core, out, chosen)
    return chosen


# ---- symbols -------------------------------------------------------------------------------

def _nm(path: Path, *flags: str) -> set[str]:
    out = run([tool("nm"), *flags, str(path)])
    names = set()
    for line in out.splitlines():
        parts = line.split()
        if parts and not line.endswith(":"):
            names.add(parts[-1])
    return names


@cache
def libgcc_symbols(target: str) -> frozenset[str]:
    """Everything the runtime library of this multilib defines (its helpers)."""
    libgcc = Path(run([tool("gcc"), *CPU_FLAGS[target], "-print-libgcc-file-name"]).strip())
    if not libgcc.is_file():
        raise McuError(f"libgcc not found for {TARGET_NAMES[target]} ({libgcc})")
    return frozenset(_nm(libgcc, "--defined-only"))


def undefined_symbols(v: Variant) -> set[str]:
    return set().union(*(_nm(o, "--undefined-only") for o in v.objects()))


def defined_symbols(v: Variant) -> set[str]:
    return set().union(*(_nm(o, "--defined-only", "--extern-only") for o in v.objects()))


def foreign_symbols(v: Variant) -> list[str]:
    """'symbol: where' for every undefined symbol that is neither the core's nor libgcc's."""
    foreign = undefined_symbols(v) - defined_symbols(v) - libgcc_symbols(v.target)
    return [f"{v.name}: {sym} ({', '.join(call_sites(v, sym))})" for sym in sorted(foreign)]


def call_sites(v: Variant, symbol: str) -> list[str]:
    """function and source line of every reference to symbol in the variant's objects."""
    sites: list[str] = []
    for obj in v.objects():
        func, line = "?", "?"
        for text in run([tool("objdump"), "-dr", "-l", str(obj)]).splitlines():
            m = re.match(r"^(\w+)\(\):$", text)
            if m:
                func = m.group(1)
            m = re.match(r"^(/\S+?|\S+\.c):(\d+)", text)
            if m:
                line = f"{Path(m.group(1)).name}:{m.group(2)}"
            if re.search(rf"R_ARM_\w+\s+{re.escape(symbol)}$", text):
                sites.append(f"{func} at {line}")
    return sorted(set(sites)) or ["?"]


# ---- prototypes ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Param:
    ctype: str   # normalised: "const uint8_t *", "uint32_t", "estop_core_t *"
    name: str

    @property
    def is_pointer(self) -> bool:
        return self.ctype.endswith("*")

    @property
    def base(self) -> str:
        """The pointed-to or plain type without const: "uint8_t", "estop_core_t"."""
        return self.ctype.replace("const ", "").rstrip("* ").strip()

    @property
    def is_const(self) -> bool:
        return self.ctype.startswith("const ")


@dataclass(frozen=True)
class Prototype:
    name: str
    result: str
    params: tuple[Param, ...]
    header: str


def _normalise(ctype: str) -> str:
    ctype = re.sub(r"\s+", " ", ctype).strip()
    ctype = re.sub(r"\s*\*\s*", " *", ctype)
    return ctype.replace("* *", "**")


_PROTO = re.compile(r"(?P<result>[A-Za-z_][\w\s\*]*?)\s*\b(?P<name>[a-z_]\w*)\s*"
                    r"\((?P<params>[^()]*)\)\s*;")


def parse_prototypes(text: str, header: str = "") -> list[Prototype]:
    """Function declarations of a C header (comments and preprocessor lines dropped)."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    text = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#"))
    text = text.replace('extern "C" {', " ")
    protos = []
    for stmt in text.split(";"):
        stmt = stmt.strip()
        if not stmt or stmt.startswith("typedef") or "{" in stmt or "}" in stmt:
            stmt = stmt.rsplit("}", 1)[-1].strip()
            if not stmt or stmt.startswith("typedef"):
                continue
        m = _PROTO.fullmatch(stmt + ";")
        if m is None:
            continue
        params: list[Param] = []
        raw = m.group("params").strip()
        if raw and raw != "void":
            for p in raw.split(","):
                pm = re.fullmatch(r"(.*?)\b(\w+)\s*", p.strip())
                if pm is None:
                    raise McuError(f"cannot read parameter {p!r} of {m.group('name')}")
                params.append(Param(_normalise(pm.group(1)), pm.group(2)))
        protos.append(Prototype(m.group("name"), _normalise(m.group("result")), tuple(params),
                                header))
    return protos


def prototypes(core: Path = CORE_DIR) -> dict[str, Prototype]:
    """Every function the core's public headers declare: its entry points."""
    found: dict[str, Prototype] = {}
    for h in public_headers(core):
        for p in parse_prototypes(h.read_text(), h.name):
            found[p.name] = p
    if not found:
        raise McuError(f"no function prototypes in {core}/*.h")
    return found


# ---- the linked image ----------------------------------------------------------------------

@dataclass
class Footprint:
    text: int           # the core's own code (its objects)
    rodata: int         # the core's own constants
    helpers: int        # libgcc code linked in for the core
    flash: int          # everything the linked image puts in flash
    data: int           # .data + .bss of the image: must be 0
    alloc_sections: dict[str, int] = field(default_factory=dict)


def _section_sizes(path: Path) -> dict[str, int]:
    with path.open("rb") as f:
        elf = ELFFile(f)
        return {s.name: s["sh_size"] for s in elf.iter_sections()
                if s["sh_flags"] & 0x2 and s["sh_size"] > 0}  # SHF_ALLOC


def footprint(v: Variant) -> Footprint:
    text = rodata = other = 0
    for obj in v.objects():
        for name, size in _section_sizes(obj).items():
            if name.startswith(".text"):
                text += size
            elif name.startswith(".rodata"):
                rodata += size
            else:
                other += size
    linked = _section_sizes(v.elf)
    flash = sum(size for name, size in linked.items() if name in (".text", ".rodata"))
    data = sum(size for name, size in linked.items() if name not in (".text", ".rodata"))
    return Footprint(text=text, rodata=rodata, helpers=flash - text - rodata, flash=flash,
                     data=data + other, alloc_sections=linked)


@dataclass(frozen=True)
class Segment:
    addr: int
    data: bytes


def load_segments(path: Path) -> tuple[list[Segment], dict[str, int]]:
    """Loadable segments and the address of every function symbol (thumb bit cleared)."""
    with path.open("rb") as f:
        elf = ELFFile(f)
        segs = [Segment(s["p_paddr"], s.data()) for s in elf.iter_segments()
                if s["p_type"] == "PT_LOAD" and s["p_filesz"] > 0]
        syms: dict[str, int] = {}
        symtab = elf.get_section_by_name(".symtab")
        if symtab is not None:
            for s in symtab.iter_symbols():
                if s["st_info"]["type"] == "STT_FUNC" and s["st_shndx"] != "SHN_UNDEF":
                    syms.setdefault(s.name, s["st_value"] & ~1)
    return segs, syms


# ---- struct layouts from DWARF -------------------------------------------------------------

Layout = list[tuple[str, int, int]]   # (member path, offset, size)


def _strip(die: Any) -> Any:
    while die.tag in ("DW_TAG_typedef", "DW_TAG_const_type", "DW_TAG_volatile_type"):
        die = die.get_DIE_from_attribute("DW_AT_type")
    return die


def _dwarf_size(die: Any) -> int:
    die = _strip(die)
    if die.tag == "DW_TAG_array_type":
        count = 1
        for sub in die.iter_children():
            if sub.tag == "DW_TAG_subrange_type":
                count *= sub.attributes["DW_AT_upper_bound"].value + 1
        return count * _dwarf_size(die.get_DIE_from_attribute("DW_AT_type"))
    return int(die.attributes["DW_AT_byte_size"].value)


def _dwarf_flatten(die: Any, prefix: str, base: int, out: Layout) -> None:
    die = _strip(die)
    if die.tag == "DW_TAG_structure_type":
        out.append((prefix or "<struct>", base, _dwarf_size(die)))
        for m in die.iter_children():
            if m.tag == "DW_TAG_member":
                name = m.attributes["DW_AT_name"].value.decode()
                off = m.attributes["DW_AT_data_member_location"].value
                _dwarf_flatten(m.get_DIE_from_attribute("DW_AT_type"),
                               f"{prefix}.{name}" if prefix else name, base + off, out)
    elif die.tag == "DW_TAG_array_type":
        item = die.get_DIE_from_attribute("DW_AT_type")
        size, isize = _dwarf_size(die), _dwarf_size(item)
        out.append((prefix, base, size))
        for i in range(size // isize):
            _dwarf_flatten(item, f"{prefix}[{i}]", base + i * isize, out)
    else:
        out.append((prefix, base, _dwarf_size(die)))


def dwarf_layouts(path: Path, names: Iterable[str]) -> dict[str, Layout]:
    """Flattened layout of each named typedef as the ARM compiler laid it out."""
    wanted = set(names)
    found: dict[str, Layout] = {}
    with path.open("rb") as f:
        elf = ELFFile(f)
        for cu in elf.get_dwarf_info().iter_CUs():
            for die in cu.iter_DIEs():
                if die.tag != "DW_TAG_typedef" or "DW_AT_name" not in die.attributes:
                    continue
                name = die.attributes["DW_AT_name"].value.decode()
                if name in wanted and name not in found:
                    layout: Layout = []
                    _dwarf_flatten(die, "", 0, layout)
                    found[name] = layout
    return found


def cffi_layout(ffi: Any, ctype: Any, prefix: str = "", base: int = 0,
                out: Layout | None = None) -> Layout:
    """The same flattening for a cffi type (the host build's layout)."""
    if out is None:
        out = []
    if isinstance(ctype, str):
        ctype = ffi.typeof(ctype)
    if ctype.kind == "struct":
        out.append((prefix or "<struct>", base, ffi.sizeof(ctype)))
        for name, fld in ctype.fields:
            cffi_layout(ffi, fld.type, f"{prefix}.{name}" if prefix else name,
                        base + fld.offset, out)
    elif ctype.kind == "array":
        isize = ffi.sizeof(ctype.item)
        out.append((prefix, base, ffi.sizeof(ctype)))
        for i in range(ctype.length):
            cffi_layout(ffi, ctype.item, f"{prefix}[{i}]", base + i * isize, out)
    else:
        out.append((prefix, base, ffi.sizeof(ctype)))
    return out


def dwarf_type_sizes(path: Path, names: Iterable[str]) -> dict[str, int]:
    """byte size of named typedefs (enums included: arm-none-eabi makes them small)."""
    wanted = set(names)
    sizes: dict[str, int] = {}
    with path.open("rb") as f:
        elf = ELFFile(f)
        for cu in elf.get_dwarf_info().iter_CUs():
            for die in cu.iter_DIEs():
                if die.tag == "DW_TAG_typedef" and "DW_AT_name" in die.attributes:
                    name = die.attributes["DW_AT_name"].value.decode()
                    if name in wanted:
                        sizes.setdefault(name, _dwarf_size(die))
    return sizes


# ---- worst-case stack ----------------------------------------------------------------------

@dataclass
class CallGraph:
    frame: dict[str, int] = field(default_factory=dict)      # node -> own frame in bytes
    calls: dict[str, set[str]] = field(default_factory=dict)  # node -> callees
    label: dict[str, str] = field(default_factory=dict)       # node -> function name
    public: set[str] = field(default_factory=set)              # the core's external functions


_NODE = re.compile(r'node: \{ title: "([^"]+)" label: "([^"\\]+)(?:\\n[^"]*?)?(?:\\n(\d+) bytes '
                   r'\((\w+(?:,\w+)?)\))?"')
_EDGE = re.compile(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"')


@dataclass
class _AsmFunc:
    name: str
    start: int
    end: int = 0
    insns: list[tuple[int, str]] = field(default_factory=list)


def _disassembly(path: Path) -> list[_AsmFunc]:
    """The functions of a linked image as objdump splits them, with their instructions."""
    funcs: list[_AsmFunc] = []
    for line in run([tool("objdump"), "-d", "--no-show-raw-insn", str(path)]).splitlines():
        m = re.match(r"^([0-9a-f]+) <([^>]+)>:$", line)
        if m:
            funcs.append(_AsmFunc(m.group(2), int(m.group(1), 16)))
            continue
        m = re.match(r"^\s+([0-9a-f]+):\t(.*)$", line)
        if m and funcs:
            funcs[-1].insns.append((int(m.group(1), 16), m.group(2).strip()))
    funcs.sort(key=lambda f: f.start)
    for f, nxt in zip(funcs, [*funcs[1:], None], strict=True):
        f.end = nxt.start if nxt is not None else (f.insns[-1][0] + 4 if f.insns else f.start)
    return funcs


def _containing(funcs: list[_AsmFunc], addr: int) -> _AsmFunc | None:
    for f in funcs:
        if f.start <= addr < f.end:
            return f
    return None


def _asm_frame(f: _AsmFunc) -> int:
    """Bytes an assembly routine (a libgcc helper) may take: every push and sp decrement
    added up, whatever path it takes (an over-estimate)."""
    total = 0
    for _, insn in f.insns:
        m = re.match(r"(?:push(?:\.w)?|stmdb(?:\.w)?\s+sp!,)\s*\{([^}]*)\}", insn)
        if m:
            for part in m.group(1).split(","):
                rng = re.fullmatch(r"r(\d+)-r(\d+)", part.strip())
                total += 4 * (int(rng.group(2)) - int(rng.group(1)) + 1 if rng else 1)
        m = re.match(r"sub(?:\.w|w)?\s+sp,\s*(?:sp,\s*)?#(\d+)", insn)
        if m:
            total += int(m.group(1))
    return total


def _asm_calls(funcs: list[_AsmFunc], f: _AsmFunc) -> set[str]:
    """Functions that f branches into (a call or a jump into another routine)."""
    calls = set()
    for _, insn in f.insns:
        op = insn.split(None, 1)[0] if insn else ""
        if op in ("blx", "bx", "mov", "ldr", "pop") and re.search(r"\bpc\b|blx\s+r|bx\s+r", insn):
            if not re.fullmatch(r"bx\s+lr|pop(?:\.w)?\s+\{[^}]*pc\}", insn):
                raise McuError(f"indirect branch in {f.name} ({insn}): no static stack bound")
        m = re.match(r"b\w*\s+([0-9a-f]+) <", insn)
        if m:
            target = _containing(funcs, int(m.group(1), 16))
            if target is None:
                raise McuError(f"{f.name} branches outside the image ({insn})")
            if target is not f:
                calls.add(target.name)
    return calls


def call_graph(v: Variant) -> CallGraph:
    """gcc's call graph of the core (.ci files, frames as in the .su files), completed with the
    libgcc helpers it calls, read from the linked image's disassembly."""
    g = CallGraph()
    for src in core_sources(v.core):
        ci = (v.dir / f"{src.stem}.ci").read_text()
        for m in _NODE.finditer(ci):
            title, label, size, kind = m.groups()
            g.label[title] = label
            if size is not None:
                if kind not in ("static", "dynamic,bounded"):
                    raise McuError(f"{v.name}: {label} has a {kind} frame: no static bound")
                g.frame[title] = int(size)
                if ":" not in title:   # static functions are titled file:name, others name
                    g.public.add(title)
        for m in _EDGE.finditer(ci):
            g.calls.setdefault(m.group(1), set()).add(m.group(2))
    funcs = _disassembly(v.elf)
    _, symbols = load_segments(v.elf)
    pending = sorted({t for callees in g.calls.values() for t in callees} - set(g.frame))
    while pending:
        name = pending.pop()
        if name in g.frame:
            continue
        f = None
        if name in symbols:
            f = _containing(funcs, symbols[name])
        else:
            f = next((x for x in funcs if x.name == name), None)
        if f is None:
            raise McuError(f"{v.name}: {name} is called but not in the image")
        g.frame[name] = _asm_frame(f)
        g.label[name] = name if f.name == name else f"{name}={f.name}"
        g.calls[name] = _asm_calls(funcs, f)
        pending.extend(g.calls[name])
    return g


def worst_stack(g: CallGraph, node: str) -> tuple[int, list[str]]:
    """Deepest sum of frames from node down, and the path that gives it. Tail calls count as
    calls (a safe over-estimate); recursion has no bound and is an error."""
    memo: dict[str, tuple[int, list[str]]] = {}

    def walk(n: str, seen: tuple[str, ...]) -> tuple[int, list[str]]:
        if n in seen:
            raise McuError(f"recursion through {g.label.get(n, n)}: no static stack bound")
        if n not in memo:
            deepest: tuple[int, list[str]] = (0, [])
            for c in sorted(g.calls.get(n, ())):
                below = walk(c, (*seen, n))
                if below[0] > deepest[0]:
                    deepest = below
            memo[n] = (g.frame[n] + deepest[0], [g.label.get(n, n), *deepest[1]])
        return memo[n]

    return walk(node, ())


def stack_per_entry(v: Variant) -> dict[str, tuple[int, list[str]]]:
    g = call_graph(v)
    result = {}
    for name in prototypes(v.core):
        if name not in g.public:
            raise McuError(f"{v.name}: {name} is declared in a header but not compiled")
        result[name] = worst_stack(g, name)
    return result
