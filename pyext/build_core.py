"""cffi (API mode) build of the firmware core into ``estop._core``.

The strict C99 warning gate runs on the core sources separately (see firmware/Makefile); the
generated wrapper is compiled with the compiler's defaults. The declarations are read from the
public headers themselves (``estop_core.h``, ``estop_blake2s.h``), so each header stays the only
description of its interface: preprocessor lines are dropped, every ``#define`` constant is
re-declared as ``#define NAME ...`` and array lengths as ``[...]``, so that the C compiler
supplies the values.

``make_builder`` also serves the instrumented builds (coverage, UndefinedBehaviorSanitizer),
which compile the very same sources under another module name.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from cffi import FFI

ROOT = Path(__file__).resolve().parent.parent
CORE_DIR = ROOT / "firmware" / "core"
HEADERS = ["estop_blake2s.h", "estop_core.h"]  # in the order the core header needs them

_DEFINE = re.compile(r"^#define\s+(ESTOP_[A-Z0-9_]+)\s+\S+")


def cdef_from_header(text: str) -> str:
    """Turns the public header into a cffi cdef."""
    decls: list[str] = []
    defines: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        match = _DEFINE.match(stripped)
        if match and match.group(1) != "ESTOP_CORE_H":
            defines.append(f"#define {match.group(1)} ...")
            continue
        if stripped.startswith("#") or stripped in ('extern "C" {', "}") and "extern" in stripped:
            continue
        decls.append(line)
    body = "\n".join(decls)
    body = re.sub(r'extern "C" \{', "", body)
    # Array lengths named by a constant: let the compiler complete them.
    body = re.sub(r"\[ESTOP_[A-Z0-9_]+\]", "[...]", body)
    return "\n".join(defines) + "\n" + body


def sources(core_dir: Path = CORE_DIR) -> list[str]:
    """Every source file of the core (its files by job, the CRCs, BLAKE2s)."""
    return sorted(p.name for p in core_dir.glob("estop_*.c"))


def make_builder(module: str, extra_compile_args: list[str] | None = None,
                 extra_link_args: list[str] | None = None, relative: bool = True,
                 core_dir: Path = CORE_DIR) -> FFI:
    ffi = FFI()
    for header in HEADERS:
        text = (core_dir / header).read_text()
        # The C++ guard's closing brace is the only bare "}" line at top level after the
        # prototypes.
        text = text.replace('#ifdef __cplusplus\n}\n#endif', "")
        ffi.cdef(cdef_from_header(text))
    base = Path(os.path.relpath(core_dir, ROOT)) if relative else core_dir
    ffi.set_source(
        module,
        "".join(f'#include "{header}"\n' for header in HEADERS),
        sources=[str(base / name) for name in sources(core_dir)],
        include_dirs=[str(base)],
        extra_compile_args=list(extra_compile_args or []),
        extra_link_args=list(extra_link_args or []),
    )
    return ffi


ffibuilder = make_builder("estop._core")

if __name__ == "__main__":
    ffibuilder.compile(verbose=True)
