"""An SMT-LIB problem with its assertions in another order (tools/proof/orders.py, and the
retry of tools/proof/solvers/cpu-limited, which runs it as a script): the same logic, which
CVC4 may answer in another time, or at all (docs/PROOF.md "Known holes").

  python3 tools/proof/reorder.py SEED IN OUT
"""

from __future__ import annotations

import random
import sys


def commands(text: str) -> list[str]:
    """The top-level S-expressions of an SMT-LIB text, without its comments."""
    out: list[str] = []
    depth, start, i, n = 0, 0, 0, len(text)
    while i < n:
        c = text[i]
        if c == ";":
            j = text.find("\n", i)
            i = n if j < 0 else j
            continue
        if c == '"':  # a string: "" is a quote inside it
            j = i + 1
            while True:
                j = text.index('"', j)
                if text.startswith('""', j):
                    j += 2
                    continue
                break
            i = j + 1
            continue
        if c == "|":  # a quoted symbol
            i = text.index("|", i + 1) + 1
            continue
        if c == "(":
            if depth == 0:
                start = i
            depth += 1
        elif c == ")":
            depth -= 1
            if depth == 0:
                out.append(text[start:i + 1])
        i += 1
    return out


def reordered(text: str, seed: int) -> str:
    """The problem with every declaration first, in its order, then the assertions, in an order
    drawn from seed (0: their own), then (check-sat) and what follows it."""
    cmds = commands(text)
    k = next(i for i, c in enumerate(cmds) if c.startswith("(check-sat"))
    decls = [c for c in cmds[:k] if not c.startswith("(assert")]
    asserts = [c for c in cmds[:k] if c.startswith("(assert")]
    if seed:
        random.Random(seed).shuffle(asserts)
    return "\n".join(decls + asserts + cmds[k:]) + "\n"


if __name__ == "__main__":
    seed, src, dst = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    with open(src, encoding="utf-8") as f:
        text = f.read()
    with open(dst, "w", encoding="utf-8") as f:
        f.write(reordered(text, seed))
