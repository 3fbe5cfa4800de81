"""The Cortex-M build of the core run in the unicorn CPU emulator, next to the host build.

``CortexM`` loads a linked image and calls a function the way a Cortex-M caller would (AAPCS:
r0-r3, then the stack; 64-bit values in an even register pair or an 8-aligned stack slot; the
result in r0, r1) and returns when the callee jumps back to a magic return address.

``ArmCore`` and ``HostCore`` give both builds one generic interface: ``call(name, values)``
with the arguments by parameter name, marshalled from the prototypes in the core's headers.
Pointers to a struct type point to one object of that type per side (the core, the output...);
byte inputs are copied in; integers are passed as they are. ``snapshot()`` returns every object's
raw bytes, so that a caller can compare the two sides byte for byte after every call.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcubuild import (
    CORE_DIR,
    McuError,
    Prototype,
    Variant,
    dwarf_layouts,
    load_segments,
    prototypes,
)
from unicorn import (
    UC_ARCH_ARM,
    UC_HOOK_BLOCK,
    UC_HOOK_CODE,
    UC_MODE_MCLASS,
    UC_MODE_THUMB,
    Uc,
    UcError,
)
from unicorn.arm_const import (
    UC_ARM_REG_LR,
    UC_ARM_REG_PC,
    UC_ARM_REG_R0,
    UC_ARM_REG_R1,
    UC_ARM_REG_R2,
    UC_ARM_REG_R3,
    UC_ARM_REG_SP,
    UC_CPU_ARM_CORTEX_M0,
    UC_CPU_ARM_CORTEX_M4,
)

FLASH_BASE, FLASH_SIZE = 0x00000000, 0x40000
RAM_BASE, RAM_SIZE = 0x20000000, 0x10000
STACK_TOP = RAM_BASE + RAM_SIZE
STACK_SIZE = 0x2000
PAINT_SIZE = 0x400                              # painted below the caller's frame to measure
RET_ADDR = FLASH_BASE + FLASH_SIZE - 0x10      # a caller's return address: the run ends there
PAINT = 0xA5
INPUT_MAX = 512                                 # room for one byte-buffer argument
OUTBUF = 64                                     # room for one byte-buffer result
CPU_MODEL = {"m0plus": UC_CPU_ARM_CORTEX_M0, "m4": UC_CPU_ARM_CORTEX_M4}  # M0 = ARMv6-M as M0+
ARG_REGS = (UC_ARM_REG_R0, UC_ARM_REG_R1, UC_ARM_REG_R2, UC_ARM_REG_R3)

# Sizes of the scalar C types the core's interface uses, on a 32-bit Cortex-M (ILP32).
ARM_SCALAR = {"uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4,
              "int32_t": 4, "uint64_t": 8, "int64_t": 8, "size_t": 4, "int": 4,
              "unsigned": 4, "unsigned int": 4, "char": 1, "_Bool": 1, "bool": 1}


class CortexM:
    """One Cortex-M CPU with the image in flash, and RAM for the caller's objects and stack."""

    def __init__(self, elf: Path, target: str, count: bool | str = False) -> None:
        """count: count executed instructions: True (or "insn") with a hook on every
        instruction, so slower; "block" with a hook on every basic block, which adds the
        block's instructions (decoded once per block: ten times faster, and the same count on
        ARMv6-M, where a block is entered only to run whole, as nothing here faults or is
        interrupted; on ARMv7-M the instructions an IT block skips would count too). The
        hook is set before any code runs: unicorn does not add it to code already translated."""
        segments, self.symbols = load_segments(elf)
        self.uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB | UC_MODE_MCLASS)
        self.uc.ctl_set_cpu_model(CPU_MODEL[target])
        self.uc.mem_map(FLASH_BASE, FLASH_SIZE)
        self.uc.mem_map(RAM_BASE, RAM_SIZE)
        for seg in segments:
            if not FLASH_BASE <= seg.addr < FLASH_BASE + FLASH_SIZE - len(seg.data):
                raise McuError(f"{elf}: segment at {seg.addr:#x} outside the flash")
            self.uc.mem_write(seg.addr, seg.data)
        self._next = RAM_BASE
        self.instructions = 0
        self.stack_used = 0
        self.counting = bool(count)
        self._block_sizes: dict[tuple[int, int], int] = {}
        if count == "block":
            self.uc.hook_add(UC_HOOK_BLOCK, self._count_block)
        elif count:
            self.uc.hook_add(UC_HOOK_CODE, self._count)

    def alloc(self, size: int, align: int = 8) -> int:
        addr = (self._next + align - 1) & ~(align - 1)
        if addr + size > STACK_TOP - STACK_SIZE:
            raise McuError("emulated RAM is full")
        self._next = addr + size
        return addr

    def write(self, addr: int, data: bytes) -> None:
        self.uc.mem_write(addr, data)

    def read(self, addr: int, size: int) -> bytes:
        return bytes(self.uc.mem_read(addr, size))

    def cstring(self, addr: int, limit: int = 256) -> bytes:
        data = self.read(addr, limit)
        end = data.find(b"\0")
        if end < 0:
            raise McuError(f"no string end within {limit} bytes at {addr:#x}")
        return data[:end]

    def call(self, func: str, args: list[tuple[int, int]],
             measure_stack: bool = False) -> tuple[int, int]:
        """Calls func with (value, size) arguments per AAPCS; returns (r0, r1). Afterwards
        self.instructions holds the count of the call (when counting) and self.stack_used
        the bytes of stack it used (when measured)."""
        regs: list[int] = []
        stack = b""
        ncrn = 0
        for value, size in args:
            if size == 8:
                lo, hi = value & 0xFFFFFFFF, (value >> 32) & 0xFFFFFFFF
                ncrn += ncrn % 2                       # an even register pair
                if ncrn <= 2:
                    regs += [0] * (ncrn - len(regs)) + [lo, hi]
                    ncrn += 2
                else:
                    ncrn = 4
                    stack += b"\0" * (-len(stack) % 8) + struct.pack("<II", lo, hi)
            elif ncrn < 4:
                regs += [0] * (ncrn - len(regs)) + [value & 0xFFFFFFFF]
                ncrn += 1
            else:
                stack += struct.pack("<I", value & 0xFFFFFFFF)
        sp = (STACK_TOP - len(stack)) & ~7             # 8-aligned at a public interface
        if stack:
            self.write(sp, stack)
        if measure_stack:
            self.write(sp - PAINT_SIZE, bytes([PAINT]) * PAINT_SIZE)
        for reg, value in zip(ARG_REGS, regs, strict=False):
            self.uc.reg_write(reg, value)
        self.uc.reg_write(UC_ARM_REG_SP, sp)
        self.uc.reg_write(UC_ARM_REG_LR, RET_ADDR | 1)
        self.instructions = 0
        try:
            self.uc.emu_start(self.symbols[func] | 1, RET_ADDR)
        except UcError as exc:
            pc = self.uc.reg_read(UC_ARM_REG_PC)
            raise McuError(f"{func}: CPU fault at pc {pc:#x}: {exc}") from exc
        if self.uc.reg_read(UC_ARM_REG_PC) != RET_ADDR:
            raise McuError(f"{func} did not return")
        if self.uc.reg_read(UC_ARM_REG_SP) != sp:
            raise McuError(f"{func} returned with a moved stack pointer")
        if measure_stack:
            # Lowest byte that no longer holds the paint, rounded to a whole word (a pushed
            # word may hold the paint value in its low bytes by chance).
            painted = self.read(sp - PAINT_SIZE, PAINT_SIZE)
            untouched = len(painted) - len(painted.lstrip(bytes([PAINT])))
            if untouched == 0:
                raise McuError(f"{func} used all {PAINT_SIZE} painted bytes of stack")
            self.stack_used = (len(painted) - untouched + 3) & ~3
        return self.uc.reg_read(UC_ARM_REG_R0), self.uc.reg_read(UC_ARM_REG_R1)

    def _count(self, uc: Uc, address: int, size: int, user: object) -> None:
        self.instructions += 1

    def _count_block(self, uc: Uc, address: int, size: int, user: object) -> None:
        n = self._block_sizes.get((address, size))
        if n is None:
            # Thumb: a halfword whose top five bits are 0b11101, 0b11110 or 0b11111 starts
            # a 32-bit instruction; any other is a 16-bit one.
            code = self.read(address, size)
            n = i = 0
            while i < size:
                hw = code[i] | (code[i + 1] << 8)
                i += 4 if (hw & 0xF800) in (0xE800, 0xF000, 0xF800) else 2
                n += 1
            self._block_sizes[(address, size)] = n
        self.instructions += n


# ---- one interface over both builds --------------------------------------------------------

@dataclass
class Result:
    """What one call did: its return value and every object's bytes afterwards."""

    ret: int | bytes | None
    objects: dict[str, bytes | int] = field(default_factory=dict)


def _is_struct_ptr(ffi: Any, base: str) -> bool:
    try:
        return bool(ffi.typeof(base).kind == "struct")
    except ffi.error:
        return False


def _signed(ffi: Any, ctype: str) -> bool:
    return bool(int(ffi.cast(ctype, -1)) < 0)


@dataclass(frozen=True)
class Arg:
    """How one parameter is passed: kind is "int", "struct" (this side's object of the type),
    "input" (bytes copied in), "outbuf" (a byte buffer the callee fills) or "scalar" (a value
    the callee writes through a pointer)."""

    name: str
    ctype: str
    base: str
    kind: str
    length_of: str | None = None    # a size_t that defaults to the length of this input


class _Side:
    """Argument rules shared by both builds."""

    def __init__(self, ffi: Any, core: Path = CORE_DIR) -> None:
        self.ffi = ffi
        self.protos: dict[str, Prototype] = prototypes(core)
        self._plans: dict[str, tuple[Arg, ...]] = {}

    def proto(self, name: str) -> Prototype:
        if name not in self.protos:
            raise McuError(f"{name} is not declared in the core's headers")
        return self.protos[name]

    def plan(self, name: str) -> tuple[Arg, ...]:
        if name not in self._plans:
            args: list[Arg] = []
            prev: Arg | None = None
            for param in self.proto(name).params:
                base = param.base
                if not param.is_pointer:
                    length_of = (prev.name if prev is not None and prev.kind == "input"
                                 and base == "size_t" else None)
                    arg = Arg(param.name, param.ctype, base, "int", length_of)
                elif _is_struct_ptr(self.ffi, base):
                    arg = Arg(param.name, param.ctype, base, "struct")
                elif base in ("uint8_t", "char", "void"):
                    arg = Arg(param.name, param.ctype, base,
                              "input" if param.is_const else "outbuf")
                else:
                    arg = Arg(param.name, param.ctype, base, "scalar")
                args.append(arg)
                prev = arg
            self._plans[name] = tuple(args)
        return self._plans[name]

    @staticmethod
    def value(fn: str, arg: Arg, values: Mapping[str, Any]) -> Any:
        """The argument's value: given by name; for a length, that of its input; for a
        pointer, ... (this side's object)."""
        if arg.name in values:
            return values[arg.name]
        if arg.length_of is not None:
            data = values.get(arg.length_of)
            return 0 if data is None else len(data)
        if arg.kind != "int":
            return ...
        raise McuError(f"{fn}: no value for parameter {arg.name}")


class HostCore(_Side):
    """The x86-64 build (the cffi module every other test uses)."""

    def __init__(self, ffi: Any, lib: Any) -> None:
        super().__init__(ffi)
        self.lib = lib
        self.objects: dict[str, Any] = {}
        self._keep: list[Any] = []

    def _object(self, key: str, ctype: str) -> Any:
        if key not in self.objects:
            self.objects[key] = self.ffi.new(ctype)
        return self.objects[key]

    def reset(self) -> None:
        self.objects.clear()

    def call(self, name: str, values: Mapping[str, Any]) -> Result:
        p = self.proto(name)
        args: list[Any] = []
        self._keep.clear()
        for arg in self.plan(name):
            v = self.value(name, arg, values)
            if arg.kind == "int":
                args.append(v)
            elif v is None:
                args.append(self.ffi.NULL)
            elif arg.kind == "struct":
                obj = self._object(arg.base, f"{arg.base} *")
                if isinstance(v, bytes | bytearray):
                    self.ffi.memmove(obj, v, len(v))
                args.append(obj)
            elif arg.kind == "input":
                buf = self.ffi.new("uint8_t[]", max(1, len(v)))
                self.ffi.memmove(buf, v, len(v))
                self._keep.append(buf)
                args.append(self.ffi.cast(arg.ctype, buf))
            elif arg.kind == "outbuf":
                obj = self._object(f"buf:{arg.name}", f"uint8_t[{OUTBUF}]")
                args.append(self.ffi.cast(arg.ctype, obj))
            else:
                args.append(self._object(f"scalar:{arg.name}", f"{arg.base} *"))
        ret = getattr(self.lib, name)(*args)
        if p.result == "void":
            out: int | bytes | None = None
        elif p.result.endswith("*"):
            out = self.ffi.string(ret) if ret != self.ffi.NULL else None
        else:
            out = int(ret)
        return Result(out, self.snapshot())

    def snapshot(self) -> dict[str, bytes | int]:
        snap: dict[str, bytes | int] = {}
        for key, obj in self.objects.items():
            snap[key] = int(obj[0]) if key.startswith("scalar:") else bytes(self.ffi.buffer(obj))
        return snap


class ArmCore(_Side):
    """A Cortex-M build in the emulator, with one object per type in its RAM."""

    def __init__(self, v: Variant, ffi: Any, count: bool | str = False) -> None:
        super().__init__(ffi, v.core)
        self.variant = v
        self.cpu = CortexM(v.elf, v.target, count)
        self.objects: dict[str, tuple[int, int, str]] = {}   # key -> (addr, size, ctype)
        self._pool: dict[str, tuple[int, int, str]] = {}     # every object ever placed
        self._inputs: dict[str, int] = {}
        self._arg_sizes: dict[str, int] = {}
        self._signed: dict[str, bool] = {}
        struct_names = [t for t in ffi.list_types()[0] if _is_struct_ptr(ffi, t)]
        self.layouts = dwarf_layouts(v.elf, struct_names)

    def sizeof(self, ctype: str) -> int:
        if ctype in self.layouts:
            return self.layouts[ctype][0][2]
        if ctype in ARM_SCALAR:
            return ARM_SCALAR[ctype]
        raise McuError(f"{self.variant.name}: size of {ctype} unknown on ARM")

    def _object(self, key: str, ctype: str, size: int) -> int:
        if key not in self.objects:
            if key not in self._pool:
                self._pool[key] = (self.cpu.alloc(size), size, ctype)
            self.objects[key] = self._pool[key]
            self.cpu.write(self._pool[key][0], bytes(size))
        return self.objects[key][0]

    def reset(self) -> None:
        """Forgets every object, as a fresh caller would have none (the CPU is kept)."""
        self.objects.clear()

    def _input(self, name: str, data: bytes) -> int:
        if len(data) > INPUT_MAX:
            raise McuError(f"input {name} longer than {INPUT_MAX} bytes")
        if name not in self._inputs:
            self._inputs[name] = self.cpu.alloc(INPUT_MAX)
        self.cpu.write(self._inputs[name], data)
        return self._inputs[name]

    def arg_size(self, ctype: str) -> int:
        """Bytes an integer argument takes in registers or on the stack (a word, or two)."""
        if ctype not in self._arg_sizes:
            kind = self.ffi.typeof(ctype).kind
            self._arg_sizes[ctype] = 4 if kind == "enum" else max(4, self.sizeof(ctype))
        return self._arg_sizes[ctype]

    def call(self, name: str, values: Mapping[str, Any], measure_stack: bool = False) -> Result:
        p = self.proto(name)
        args: list[tuple[int, int]] = []
        for arg in self.plan(name):
            v = self.value(name, arg, values)
            if arg.kind == "int":
                args.append((int(v), self.arg_size(arg.ctype)))
                continue
            if v is None:
                addr = 0
            elif arg.kind == "struct":
                addr = self._object(arg.base, arg.base, self.sizeof(arg.base))
                if isinstance(v, bytes | bytearray):
                    self.cpu.write(addr, bytes(v))
            elif arg.kind == "input":
                addr = self._input(arg.name, bytes(v))
            elif arg.kind == "outbuf":
                addr = self._object(f"buf:{arg.name}", "uint8_t", OUTBUF)
            else:
                addr = self._object(f"scalar:{arg.name}", arg.base, self.sizeof(arg.base))
            args.append((addr, 4))
        r0, r1 = self.cpu.call(name, args, measure_stack=measure_stack)
        out: int | bytes | None
        if p.result == "void":
            out = None
        elif p.result.endswith("*"):
            out = self.cpu.cstring(r0) if r0 else None
        else:
            # AAPCS: a result narrower than a word comes back extended to a word in r0, so r0
            # is read whole (a callee that did not extend shows up as a difference).
            bits = 8 * self.arg_size(p.result)
            raw = r0 | (r1 << 32) if bits == 64 else r0
            if p.result not in self._signed:
                self._signed[p.result] = _signed(self.ffi, p.result)
            out = raw - (1 << bits) if self._signed[p.result] and raw >> (bits - 1) else raw
        return Result(out, self.snapshot())

    def snapshot(self) -> dict[str, bytes | int]:
        snap: dict[str, bytes | int] = {}
        for key, (addr, size, _) in self.objects.items():
            data = self.cpu.read(addr, size)
            snap[key] = int.from_bytes(data, "little") if key.startswith("scalar:") else data
        return snap

    def field_at(self, ctype: str, offset: int) -> str:
        """The innermost member at a byte offset (for a readable difference)."""
        best = "?"
        for path, off, size in self.layouts.get(ctype, []):
            if off <= offset < off + size:
                best = path
        return best


def difference(arm: ArmCore, host: Result, got: Result) -> str | None:
    """None when both results are equal byte for byte, else the first difference in words."""
    if host.ret != got.ret:
        return f"return value: host {host.ret!r}, {arm.variant.name} {got.ret!r}"
    for key in sorted(set(host.objects) | set(got.objects)):
        a, b = host.objects.get(key), got.objects.get(key)
        if a == b:
            continue
        if isinstance(a, bytes) and isinstance(b, bytes) and len(a) == len(b):
            i = next(i for i in range(len(a)) if a[i] != b[i])
            member = arm.field_at(key, i)
            return (f"{key} byte {i} ({member}): host {a[i]:#04x}, "
                    f"{arm.variant.name} {b[i]:#04x}")
        return f"{key}: host {a!r}, {arm.variant.name} {b!r}"
    return None
