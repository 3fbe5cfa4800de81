"""Builds the core once more, instrumented for gcov and UndefinedBehaviorSanitizer.

Usage: ``python pyext/build_instrumented.py OUTDIR``. The module ``_estop_core_cov`` lands in
OUTDIR together with the .gcno/.gcda files; select it with ESTOP_CORE_MODULE=_estop_core_cov
and PYTHONPATH=OUTDIR. Any undefined behaviour aborts the process, so it fails the tests.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from build_core import make_builder  # noqa: E402

# Python's own CFLAGS carry -fwrapv, which makes signed overflow defined and so invisible to
# UBSan; the core is C99 without it, so the instrumented build turns it off again.
SANITIZE = ["-fsanitize=undefined", "-fno-sanitize-recover=undefined", "-fno-wrapv"]


def main(outdir: str) -> None:
    builder = make_builder(
        "_estop_core_cov",
        extra_compile_args=["-O0", "-g", "--coverage", "-fno-omit-frame-pointer", *SANITIZE],
        extra_link_args=["--coverage", *SANITIZE],
        relative=False,
    )
    builder.compile(tmpdir=outdir, verbose=False)


if __name__ == "__main__":
    main(sys.argv[1])
