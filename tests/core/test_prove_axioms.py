"""The axioms of make prove (prove/assumed.txt), read from the files WP reads and evaluated:
the byte facts for every pair of bytes, the wrap rules of C99 6.3.1.3p2 at their edges and
across their range. An axiom edited into something false fails here before a proof rests on it.
"""

from __future__ import annotations

import random
import re
from collections.abc import Callable
from pathlib import Path

from repo import ROOT

PROVE = ROOT / "prove"


def axioms(path: Path, block: str) -> dict[str, str]:
    """name -> the formula of each axiom of an axiomatic block."""
    body = re.search(r"axiomatic " + block + r" \{(.*?)\n  \}", path.read_text(), re.S)
    assert body, f"no axiomatic {block} in {path}"
    return {m.group(1): " ".join(m.group(2).split())
            for m in re.finditer(r"axiom (\w+):(.*?);\s*(?=axiom|\Z)", body.group(1) + " ", re.S)}


def as_python(formula: str, variables: str) -> Callable[..., bool]:
    """\\forall integer <variables>; A ==> B, in the subset these axioms use, as a function.
    A cast (uint32_t)x is the C conversion: x reduced modulo 2^32."""
    m = re.fullmatch(r"\\forall integer " + re.escape(variables) + r"; (.*)",
                     formula.strip().rstrip(";"))
    assert m, formula
    hyp, concl = m.group(1).split("==>")

    def py(expr: str) -> str:
        expr = expr.replace("&&", " and ")
        return re.sub(r"\(uint32_t\)(\w+)", r"u32(\1)", expr)

    source = f"lambda {variables}: (not ({py(hyp)})) or ({py(concl)})"
    return eval(source, {"u32": lambda v: v % 2**32})  # type: ignore[no-any-return]  # noqa: S307


def test_every_byte_axiom_holds_for_every_pair() -> None:
    found = axioms(PROVE / "logic.h", "ByteBits")
    assert set(found) == {"or_byte", "xor_byte"}, found
    for name, formula in found.items():
        check = as_python(formula, "x, y")
        bad = [(x, y) for x in range(-2, 258) for y in range(-2, 258) if not check(x, y)]
        assert not bad, f"axiom {name} is false for {bad[:3]}"


def test_the_wrap_axioms_hold_at_their_edges_and_inside() -> None:
    found = axioms(PROVE / "predicates.h", "U32Wrap")
    assert set(found) == {"u32_wrap_up", "u32_wrap_down"}, found
    rng = random.Random(24)
    edges = [-2**32 - 1, -2**32, -2**32 + 1, -1, 0, 1, 2**32 - 1, 2**32, 2**32 + 1,
             2**33 - 1, 2**33, 2**33 + 1]
    samples = edges + [rng.randrange(-2**33, 2**34) for _ in range(20000)]
    for name, formula in found.items():
        check = as_python(formula, "x")
        bad = [x for x in samples if not check(x)]
        assert not bad, f"axiom {name} is false for {bad[:3]}"


def test_the_check_fails_on_a_false_axiom() -> None:
    wrong = as_python("\\forall integer x, y; 0 <= x <= 255 && 0 <= y <= 255 ==> "
                      "0 <= (x + y) <= 255;", "x, y")
    assert not all(wrong(x, y) for x in range(256) for y in range(256))
    off_by_one = as_python("\\forall integer x; 4294967296 <= x < 8589934592 ==> "
                           "(uint32_t)x == x - 4294967295;", "x")
    assert not off_by_one(2**32)
