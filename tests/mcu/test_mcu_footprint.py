"""The Cortex-M builds against the footprint budget of issue 10, and the analysis behind it.

- nothing but the core and libgcc's runtime helpers is referenced (no libc);
- flash (text + rodata) of the whole core on M0+ at -Os: at most 8 KiB;
- sizeof(estop_core_t) at most 1 KiB; no .data or .bss;
- the worst-case stack of every entry point (frames from -fstack-usage summed along the deepest
  path of the call graph) at most 512 bytes on M0+ at -Os.
"""

from __future__ import annotations

import pytest

from estop.core import ffi, lib
from mcu_util import ensure_built, mcubuild

ALL = [v.name for v in mcubuild.VARIANTS]
STACK_BUDGETED = list(mcubuild.BUDGET_STACK_VARIANTS)


@pytest.mark.parametrize("name", ALL)
def test_only_the_core_and_libgcc_helpers_are_referenced(name: str) -> None:
    ensure_built()
    v = mcubuild.variant(name)
    assert mcubuild.foreign_symbols(v) == []
    needed = mcubuild.undefined_symbols(v) - mcubuild.defined_symbols(v)
    assert needed <= mcubuild.libgcc_symbols(v.target)
    assert not {"memset", "memcpy", "memmove", "memcmp", "__aeabi_memclr"} & needed


def test_the_symbol_check_names_a_libc_call() -> None:
    """The check is not vacuous: memset is not in libgcc, so a core that needed it fails."""
    ensure_built()
    for target in mcubuild.TARGETS:
        helpers = mcubuild.libgcc_symbols(target)
        assert "__aeabi_uidiv" in helpers and "memset" not in helpers and "memcpy" not in helpers


def test_flash_of_the_whole_core_on_m0plus_at_Os() -> None:
    ensure_built()
    fp = mcubuild.footprint(mcubuild.variant("m0plus-Os"))
    assert fp.text > 1000
    assert fp.flash == fp.text + fp.rodata + fp.helpers
    assert fp.flash <= mcubuild.BUDGET_FLASH, fp


@pytest.mark.parametrize("name", ALL)
def test_no_data_or_bss(name: str) -> None:
    ensure_built()
    fp = mcubuild.footprint(mcubuild.variant(name))
    assert fp.data == 0
    assert set(fp.alloc_sections) <= {".text", ".rodata"}, fp.alloc_sections


def test_state_size() -> None:
    ensure_built()
    assert ffi.sizeof("estop_core_t") <= mcubuild.BUDGET_STATE
    for v in mcubuild.VARIANTS:
        layout = mcubuild.dwarf_layouts(v.elf, ["estop_core_t"])["estop_core_t"]
        assert layout[0][2] <= mcubuild.BUDGET_STATE


@pytest.mark.parametrize("name", STACK_BUDGETED)
def test_worst_case_stack_of_every_entry_point_on_m0plus(name: str) -> None:
    """M0+ at -Os (the build of the flash budget). M0+ at -O2 is reported by make mcu: its
    BLAKE2s compression frame is larger and the authenticated paths go past 512 bytes."""
    ensure_built()
    stacks = mcubuild.stack_per_entry(mcubuild.variant(name))
    # Every function of the C API (the cffi module's) is an entry point with a bound.
    api = {n for n in dir(lib) if n.startswith("estop_") and callable(getattr(lib, n))}
    assert api <= set(stacks)
    over = {fn: s for fn, s in stacks.items() if s[0] > mcubuild.BUDGET_STACK}
    assert not over, over
    # The frame of the state machine's deepest path is counted, CRC included.
    depth, path = stacks["estop_tcp_rx"]
    assert depth >= 64 and path[0] == "estop_tcp_rx" and len(path) >= 3


def test_stack_bound_counts_libgcc_helpers() -> None:
    """On M0+ (no divide instruction) the division helpers are in the graph with a frame."""
    ensure_built()
    g = mcubuild.call_graph(mcubuild.variant("m0plus-Os"))
    helpers = [n for n in g.frame if n.startswith("__aeabi_")]
    assert helpers and all(n in g.frame for n in helpers)


# -- the analysis on inputs made up for the purpose -----------------------------------------------
def test_asm_frame_counts_pushes_and_sp_decrements() -> None:
    f = mcubuild._AsmFunc("h", 0, 16, [(0, "push\t{r4, r5, lr}"), (2, "sub\tsp, #16"),
                                      (4, "push\t{r0-r3}"), (6, "stmdb\tsp!, {r4, r5}"),
                                      (8, "bx\tlr")])
    assert mcubuild._asm_frame(f) == 12 + 16 + 16 + 8


def test_worst_stack_takes_the_deepest_path_and_refuses_recursion() -> None:
    g = mcubuild.CallGraph(frame={"a": 8, "b": 16, "c": 40, "d": 4},
                           calls={"a": {"b", "c"}, "b": {"d"}, "c": set()})
    assert mcubuild.worst_stack(g, "a") == (48, ["a", "c"])
    g.calls["d"] = {"a"}
    with pytest.raises(mcubuild.McuError, match="recursion"):
        mcubuild.worst_stack(g, "a")


def test_prototypes_are_read_from_the_headers() -> None:
    protos = mcubuild.parse_prototypes(
        "/* x(int y); */\n#define A(b) (b)\ntypedef struct { uint32_t a; } t_t;\n"
        "estop_err_t estop_mac(const uint8_t *key, size_t key_len,\n"
        "                      uint64_t session, uint8_t *tag);\nvoid estop_none(void);\n")
    assert [p.name for p in protos] == ["estop_mac", "estop_none"]
    mac = protos[0]
    assert [(q.ctype, q.name) for q in mac.params] == [
        ("const uint8_t *", "key"), ("size_t", "key_len"), ("uint64_t", "session"),
        ("uint8_t *", "tag")]
    assert protos[1].params == ()
    real = mcubuild.prototypes()
    assert "estop_tcp_rx" in real and len(real["estop_tcp_rx"].params) == 7


def test_instruction_count_scenario() -> None:
    """The scenario of make mcu and bench/mcu_instructions.py runs on every image, and its
    counts rank as they must: more work, more instructions."""
    import mcuinsns
    ensure_built()
    for v in mcubuild.VARIANTS:
        counts = {c.label: c.instructions for c in mcuinsns.scenario(v, ffi, lib)}
        assert all(n > 0 for n in counts.values()), v.name
        assert (counts["tick, nothing due"] < counts["tick, brake frame due"]
                < counts["tick, brake + status frames due"]), v.name
