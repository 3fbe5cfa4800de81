"""The differential tests compare raw bytes, which is only right when the host (x86-64 SysV)
and the Cortex-M builds (AAPCS) lay the structs out the same: checked here member by member,
from the ARM images' DWARF against the cffi module, not assumed. Also checks the emulator's
calling convention (64-bit arguments in an even register pair or an 8-aligned stack slot) on
a small function compiled for the occasion."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from estop.core import ffi, lib
from mcu_util import ArmCore, CortexM, HostCore, ensure_built, mcubuild

STRUCTS = [t for t in ffi.list_types()[0] if ffi.typeof(t).kind == "struct"]


@pytest.mark.parametrize("name", [v.name for v in mcubuild.VARIANTS])
def test_every_struct_has_the_host_layout(name: str) -> None:
    ensure_built()
    v = mcubuild.variant(name)
    arm = mcubuild.dwarf_layouts(v.elf, STRUCTS)
    assert set(arm) == set(STRUCTS), "struct types missing from the image's debug info"
    for struct in STRUCTS:
        host = mcubuild.cffi_layout(ffi, struct)
        assert arm[struct] == host, f"{struct} is laid out differently on {name}"
    # Not vacuous: every member of the state down to each byte of the TCP slots.
    assert len(arm["estop_core_t"]) > 100
    assert ("out", 0, 0) not in arm["estop_core_t"]


def test_enums_are_small_on_arm_so_no_struct_may_hold_one() -> None:
    """arm-none-eabi uses the AAPCS 'small enums' (the object attribute says so): estop_err_t
    is one byte on the MCU and four on the host. It is only ever returned (extended to a word
    in r0), never a struct member; the layout test above would catch one that became one."""
    ensure_built()
    v = mcubuild.variant("m0plus-Os")
    assert mcubuild.dwarf_type_sizes(v.elf, ["estop_err_t"]) == {"estop_err_t": 1}
    assert ffi.sizeof("estop_err_t") == 4
    attrs = subprocess.run([mcubuild.tool("readelf"), "-A", str(v.elf)], capture_output=True,
                           text=True, check=True).stdout
    assert "Tag_ABI_enum_size: small" in attrs


def test_state_sizes_match_the_host() -> None:
    ensure_built()
    for v in mcubuild.VARIANTS:
        sizes = {t: layout[0][2] for t, layout in mcubuild.dwarf_layouts(v.elf, STRUCTS).items()}
        assert sizes == {t: ffi.sizeof(t) for t in STRUCTS}, v.name


ABI_PROBE = r"""
#include <stdint.h>
/* Mixes every argument so that a misplaced one changes the result. */
uint64_t probe(uint32_t a, uint64_t b, uint32_t c, uint64_t d, uint32_t e, uint16_t f)
{
    return (b * 3u) ^ (d << 1) ^ ((uint64_t)a << 40) ^ ((uint64_t)c << 20) ^ e ^
           ((uint64_t)f << 56);
}
int32_t negative(int32_t x) { return -x; }
"""


def test_aapcs_arguments_in_the_emulator(tmp_path: Path) -> None:
    """a in r0, b in r2:r3 (r1 skipped), c, d (8-aligned), e and f on the stack; a 64-bit
    result in r0:r1. Also the instruction counter, on a function of known length."""
    ensure_built()
    src = tmp_path / "probe.c"
    src.write_text(ABI_PROBE)
    elf = tmp_path / "probe.elf"
    for target in mcubuild.TARGETS:
        subprocess.run([mcubuild.tool("gcc"), *mcubuild.CPU_FLAGS[target], "-O2", "-std=c99",
                        "-ffreestanding", "-nostdlib", "-T",
                        str(mcubuild.MAKEFILE_DIR / "core.ld"), "-Wl,--no-warn-rwx-segments",
                        "-o", str(elf), str(src), "-lgcc"], check=True)
        cpu = CortexM(elf, target, count=True)
        a, b, c, d, e, f = 0x11, 0x0123456789ABCDEF, 0x22, 0xFEDCBA9876543210, 0x33, 0xBEEF
        want = ((b * 3) ^ (d << 1) ^ (a << 40) ^ (c << 20) ^ e ^ (f << 56)) & (2**64 - 1)
        r0, r1 = cpu.call("probe", [(a, 4), (b, 8), (c, 4), (d, 8), (e, 4), (f, 4)])
        assert r0 | (r1 << 32) == want, target
        r0, _ = cpu.call("negative", [(5, 4)])
        assert r0 == 0xFFFFFFFB
        assert cpu.instructions == 2      # negs r0, r0; bx lr: the counter sees each one


def test_the_return_code_comes_back_signed() -> None:
    """estop_err_t (a one-byte enum on ARM) is read from r0 as the callee extended it."""
    ensure_built()
    arm = ArmCore(mcubuild.variant("m0plus-Os"), ffi)
    host = HostCore(ffi, lib)
    for fn, values in (("estop_tick", {"core": None, "now_us": 0}),
                       ("estop_tcp_open", {"slot": 99, "now_us": 0})):
        assert arm.call(fn, values).ret == host.call(fn, values).ret < 0
