"""The core parsed once for the WP runs of a `make prove` over it: `frama-c -save` after the
parse, and `-load` in each run instead of the parse. The parse (the preprocessor, ACSL's typing,
CIL's normalisation, the inlining of prove/wp_inline.txt) took 1.4 CPU-s a run, a load 0.4, in
each of the 19 runs of firmware/core (issue 24's fiftieth round; the ct run's goals and
verdicts were the same both ways).

A saved state is named by a digest of the parse's arguments, of every file it reads from the
core's folder and prove/, and of the frama-c that parsed: a run whose sources differ from the
saved ones (a planted copy, or an edit during the run) finds no state of its own and parses,
as before."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

from .frama import BUILD, PROVE, frama_c

SAVE_TIMEOUT_S = 300  # a hang guard: the parse takes seconds


def state_path(core_dir: Path, parse: list[str], into: Path = BUILD) -> Path:
    """Where the state of this parse is saved: <into>/parsed-<digest>.sav. The digest holds
    the frama-c that parsed too (its path, size and time): a state saved before an upgrade is
    not loaded after it."""
    exe = shutil.which("frama-c")
    st = os.stat(exe) if exe else None
    h = hashlib.sha256(f"{exe} {st.st_size} {st.st_mtime_ns}".encode() if st else b"-")
    h.update(b"\0" + "\0".join(parse).encode())
    for f in sorted([*core_dir.glob("*.[ch]"), *PROVE.glob("*.h")]):
        h.update(b"\0" + str(f).encode() + b"\0" + f.read_bytes())
    return into / f"parsed-{h.hexdigest()[:16]}.sav"


def head(core_dir: Path, parse: list[str], into: Path = BUILD) -> list[str]:
    """The arguments that give a run the parsed core: -load of its saved state when there is
    one for these sources, the parse itself otherwise."""
    state = state_path(core_dir, parse, into)
    return ["-load", str(state)] if state.is_file() else parse


def save(core_dir: Path, parse: list[str], env: dict[str, str], into: Path = BUILD) -> Path:
    """Parse once and save the state in into, the states of other sources removed;
    RuntimeError with the end of Frama-C's output when the parse fails."""
    state = state_path(core_dir, parse, into)
    part = state.with_suffix(".part")
    rc, out = frama_c([*parse, "-save", str(part)], into / "parse.log", SAVE_TIMEOUT_S, env)
    if rc != 0 or not part.is_file():
        raise RuntimeError(f"frama-c exited {rc}: {out.strip()[-300:]}")
    # put in place whole: a run that loads it meanwhile (a test beside make prove) reads
    # either state, never a part of one
    part.replace(state)
    for old in into.glob("parsed-*.sav"):
        if old != state:
            old.unlink()
    return state
