"""The OCaml module every WP run loads (task_idle.ml says why), compiled once.

frama-c -load-script compiles a script beside it at each run and removes the result: two runs
that start together race on it ("cannot load plug-in task_idle", issue 24's forty-seventh
round). Here each build compiles in a directory of its own and renames its module into place,
named by a hash of the source, the compiler and Frama-C's library path, so that concurrent builds
each finish with the same whole file and a changed script is built again."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

from .frama import BUILD, ROOT

SOURCE = ROOT / "tools" / "proof" / "task_idle.ml"
OCAMLOPT = "ocamlopt"  # Debian's ocaml-nox, the compiler that built frama-c-base
_LOCK = threading.Lock()  # one build per process; other processes race harmlessly
_BUILT: dict[tuple[Path, Path], Path] = {}


def _run(args: list[str], cwd: Path | None = None) -> str:
    res = subprocess.run(args, capture_output=True, text=True, timeout=120, check=False,
                         cwd=cwd)
    if res.returncode != 0:
        why = " ".join((res.stderr or res.stdout).split())[-500:]  # one line
        raise RuntimeError(f"{' '.join(args)}: exit {res.returncode}: {why}")
    return res.stdout.strip()


def module(source: Path = SOURCE, build: Path | None = None) -> Path:
    """The compiled module of source (.cmxs), under build (BUILD by default): built if absent."""
    build = build or BUILD
    with _LOCK:
        done = _BUILT.get((source, build))
        if done is not None and done.exists():
            return done
        if shutil.which(OCAMLOPT) is None:
            raise RuntimeError(f"{OCAMLOPT} not found (scripts/ensure-debs prove)")
        libpath = _run(["frama-c", "-print-libpath"])
        key = hashlib.sha256(source.read_bytes() + _run([OCAMLOPT, "-version"]).encode()
                             + libpath.encode()).hexdigest()[:16]
        out = build / f"{source.stem}-{key}.cmxs"
        if not out.exists():
            build.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=build, prefix=f"{source.stem}-") as tmp:
                src = Path(tmp) / source.name
                shutil.copyfile(source, src)
                _run([OCAMLOPT, "-shared", "-I", libpath, "-o", f"{source.stem}.cmxs",
                      source.name], cwd=Path(tmp))
                (Path(tmp) / f"{source.stem}.cmxs").replace(out)
        _BUILT[(source, build)] = out
        return out
