"""Mutation testing of the firmware core: do the core tests notice a planted bug?

Each mutant changes one spot of firmware/core/estop_core.c (a comparison, a constant, a
branch), is built into its own cffi module and faces the core tests. A mutant the tests pass
"survived": either the tests miss a behaviour or the change is equivalent. Prints one line a
mutant and the kill ratio; exits 1 when any mutant survives.
Usage: .venv/bin/python tools/mutants.py [--examples N]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "pyext"))

from build_core import CORE_DIR, make_builder  # noqa: E402

TESTS = ["tests/test_core_rules.py", "tests/test_core_c_api.py", "tests/test_spec_vectors.py",
         "tests/test_core_properties.py", "tests/test_core_stateful.py"]

# (name, exact text in estop_core.c, replacement). Each text must occur exactly once.
MUTANTS = [
    ("timeout >= becomes >", "(link_age(core) >= core->cfg.timeout_us)",
     "(link_age(core) > core->cfg.timeout_us)"),
    ("warn >= becomes >", "(link_age(core) >= core->cfg.warn_us)",
     "(link_age(core) > core->cfg.warn_us)"),
    ("release count >= becomes >", "(core->valid_run >= core->cfg.release_packets)",
     "(core->valid_run > core->cfg.release_packets)"),
    ("neutral check dropped", "} else if (core->last_neutral == 0u) {", "} else if (0) {"),
    ("-0.0 not neutral", "((bits & FLOAT_SIGN_BIT) != 0u) || (bits == 0u)",
     "((bits & FLOAT_SIGN_BIT) != 0u)"),
    ("range allows 1.0000001", "(bits & FLOAT_ABS_MASK) <= FLOAT_ONE_BITS",
     "(bits & FLOAT_ABS_MASK) <= (FLOAT_ONE_BITS + 1u)"),
    ("turn 4 allowed", "(turn <= 3u)", "(turn <= 4u)"),
    ("horn 2 allowed", "(horn <= 1u)", "(horn <= 2u)"),
    ("gear 3 allowed", "(gear == 1u) || (gear == 2u)",
     "(gear == 1u) || (gear == 3u) || (gear == 2u)"),
    ("19-byte packets", "((len == ESTOP_UDP_LEN) || (len == ESTOP_UDP_LEN_NO_HORN))",
     "((len >= ESTOP_UDP_LEN_NO_HORN) && (len <= ESTOP_UDP_LEN))"),
    ("stop keeps release count",
     "    core->valid_run = 0u;\n    if (core->state == ESTOP_STATE_ARMED) {",
     "    if (core->state == ESTOP_STATE_ARMED) {"),
    ("stop overwrites reason",
     "    if (core->state == ESTOP_STATE_ARMED) {\n        core->state = (uint8_t)ESTOP_STATE_ST",
     "    if (1) {\n        core->state = (uint8_t)ESTOP_STATE_ST"),
    ("no frame on change", "    out->state_changed = 1u;\n    send_brake(core, out);",
     "    out->state_changed = 1u;"),
    ("period not restarted",
     "    core->brake_due_us = core->now_us + core->cfg.brake_period_us;\n}", "}"),
    ("counter modulo 16", "#define COUNTER_MODULO 15u", "#define COUNTER_MODULO 16u"),
    ("brake level 99", "#define BRAKE_LEVEL_FULL 100u", "#define BRAKE_LEVEL_FULL 99u"),
    ("no wrap latch", "        core->link_fresh = 0u; /* latched", "        (void)0; /* latched"),
    ("backwards tick ignored", "    if (step > ESTOP_MAX_STEP_US) {", "    if (0) {"),
    ("deadline missing from next call",
     "        next = earliest(core->now_us, next, core->last_valid_us + core->cfg.timeout_us);",
     "        (void)0;"),
    ("bad crc not closing", "        out->close_slot = 1u;", "        (void)0;"),
    ("unknown id acked", "        nak = (uint8_t)ESTOP_NAK_UNKNOWN_ID;", "        (void)0;"),
    ("grid drift", "    uint32_t next = due + period;", "    uint32_t next = now + period + 1u;"),
    ("status window not reset", "    core->status_valid = 0u;\n    core->status_invalid = 0u;", ""),
    ("invalid packet keeps alive", "            core->counters.udp_invalid++;",
     "            core->counters.udp_invalid++;\n            core->last_valid_us = now_us;"),
]


def run_mutant(name: str, old: str, new: str, examples: int, work: Path) -> bool:
    """True when the tests kill the mutant."""
    src = (CORE_DIR / "estop_core.c").read_text()
    if src.count(old) != 1:
        raise SystemExit(f"mutants: error: mutant {name!r} does not match exactly once")
    core = work / "core"
    shutil.rmtree(core, ignore_errors=True)
    shutil.copytree(CORE_DIR, core)
    (core / "estop_core.c").write_text(src.replace(old, new))
    build = work / "build"
    shutil.rmtree(build, ignore_errors=True)
    build.mkdir(parents=True)
    make_builder("_estop_mutant", relative=False, core_dir=core).compile(tmpdir=str(build))
    env = dict(os.environ, PYTHONPATH=str(build), ESTOP_CORE_MODULE="_estop_mutant",
               ESTOP_STATEFUL_EXAMPLES=str(examples))
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                             *TESTS], cwd=ROOT, env=env, capture_output=True, timeout=600)
    return result.returncode != 0


def main() -> int:
    parser = argparse.ArgumentParser(description="mutation testing of the firmware core")
    parser.add_argument("--examples", type=int, default=300,
                        help="stateful examples per mutant (default 300)")
    parser.add_argument("--only", default="", help="run the mutants whose name contains this")
    args = parser.parse_args()
    chosen = [m for m in MUTANTS if args.only in m[0]]
    killed = 0
    work = ROOT / "build" / "mutants"
    try:
        for index, (name, old, new) in enumerate(chosen):
            # A fresh folder each: distutils remembers folders it made, even once removed.
            dead = run_mutant(name, old, new, args.examples, work / f"m{index}")
            killed += dead
            sys.stdout.write(f"{'killed  ' if dead else 'SURVIVED'} {name}\n")
            sys.stdout.flush()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    sys.stdout.write(f"mutants killed: {killed}/{len(chosen)}\n")
    return 0 if killed == len(chosen) else 1


if __name__ == "__main__":
    sys.exit(main())
