"""Pair the messages of a recorded stream with those of its replay, as ``diff`` pairs lines.

A replay that loses one GPS sentence publishes one fix fewer; pairing the two streams by
index would then call every later message different. Instead the streams are aligned first
and diffed after, in two steps:

1. **Content.** Each message becomes a key: its type and its fields, floats rounded to the
   field's tolerance. :class:`difflib.SequenceMatcher` (no junk heuristic) finds the longest
   runs of equal keys in order; those pairs *match*. What lies between two runs is a gap
   with ``a`` recorded and ``b`` replayed messages.
2. **Gaps.** A gap with ``a == b`` pairs its messages in order (a changed driver setting
   changes every message's values but not their number: each pair then *differs* in named
   fields, or matches after all when a rounded key straddled a boundary). A gap with
   ``a != b`` is aligned by edit distance: pairing two messages costs the share of their
   fields that differ (0..1), leaving one out costs 1, so one extra or missing message is
   one *insertion* or *deletion* and the rest still pair. Gaps too large for that
   (``MAX_DP_CELLS``) pair in order and report the surplus at the gap's end.

The order of each stream is kept: a replayed message is never paired with a recorded one
out of order. The result is a list of :class:`Pair` in stream order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from difflib import SequenceMatcher
from typing import Any, Callable, Hashable, Literal, Sequence

MAX_DP_CELLS = 250_000   # a*b of a gap aligned by edit distance (a few seconds of Python at most)

PairKind = Literal["match", "differ", "deleted", "inserted"]


@dataclass(frozen=True)
class Pair:
    """One step of the alignment: indexes into the recorded and replayed streams (None on a gap)."""

    kind: PairKind
    rec: int | None
    rep: int | None


def _rounded(value: Any, step: float) -> Hashable:
    """*value* as a hashable key, floats quantised to *step* (NaN and infinities kept apart)."""
    if isinstance(value, bool) or not isinstance(value, (float, list, tuple, dict)):
        return value if isinstance(value, Hashable) else repr(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return repr(value)
        return round(value / step) if step > 0 else value
    if isinstance(value, dict):
        return tuple(sorted((k, _rounded(v, step)) for k, v in value.items()))
    return tuple(_rounded(v, step) for v in value)


def content_key(type_name: str, fields: dict[str, Any], step_of: Callable[[str], float]) -> Hashable:
    """The key two messages share when they are equal within their fields' tolerances."""
    return (type_name, tuple(sorted((name, _rounded(v, step_of(name))) for name, v in fields.items())))


def align_streams(rec_keys: Sequence[Hashable], rep_keys: Sequence[Hashable], *,
                  pair_cost: Callable[[int, int], float]) -> list[Pair]:
    """Align two streams given their content keys; *pair_cost(i, j)*: 0 when recorded *i* equals
    replayed *j* within tolerance, up to 1 when every field differs."""
    pairs: list[Pair] = []
    matcher = SequenceMatcher(None, list(rec_keys), list(rep_keys), autojunk=False)
    for tag, i1, i2, j1, j2 in matcher.get_opcodes():
        if tag == "equal":
            pairs.extend(Pair("match", i1 + k, j1 + k) for k in range(i2 - i1))
        else:
            pairs.extend(_align_gap(i1, i2, j1, j2, pair_cost=pair_cost))
    return pairs


def _paired(i: int, j: int, pair_cost: Callable[[int, int], float]) -> Pair:
    return Pair("match" if pair_cost(i, j) == 0 else "differ", i, j)


def _align_gap(i1: int, i2: int, j1: int, j2: int, *, pair_cost: Callable[[int, int], float]) -> list[Pair]:
    """Pairs for the recorded messages i1..i2 and the replayed j1..j2 between two equal runs."""
    a, b = i2 - i1, j2 - j1
    if a == b or a == 0 or b == 0 or a * b > MAX_DP_CELLS:
        n = min(a, b)
        out = [_paired(i1 + k, j1 + k, pair_cost) for k in range(n)]
        out += [Pair("deleted", i, None) for i in range(i1 + n, i2)]
        out += [Pair("inserted", None, j) for j in range(j1 + n, j2)]
        return out
    # edit distance: cost[i][j] aligns the first i recorded with the first j replayed of the gap
    inf = float("inf")
    cost = [[inf] * (b + 1) for _ in range(a + 1)]
    step = [[""] * (b + 1) for _ in range(a + 1)]
    cost[0][0] = 0.0
    for i in range(a + 1):
        for j in range(b + 1):
            here = cost[i][j]
            if i < a and here + 1 < cost[i + 1][j]:
                cost[i + 1][j], step[i + 1][j] = here + 1, "D"
            if j < b and here + 1 < cost[i][j + 1]:
                cost[i][j + 1], step[i][j + 1] = here + 1, "I"
            if i < a and j < b:
                c = here + pair_cost(i1 + i, j1 + j)
                if c < cost[i + 1][j + 1]:
                    cost[i + 1][j + 1], step[i + 1][j + 1] = c, "P"
    out: list[Pair] = []
    i, j = a, b
    while i or j:
        move = step[i][j]
        if move == "P":
            i, j = i - 1, j - 1
            out.append(_paired(i1 + i, j1 + j, pair_cost))
        elif move == "D":
            i -= 1
            out.append(Pair("deleted", i1 + i, None))
        else:
            j -= 1
            out.append(Pair("inserted", None, j1 + j))
    out.reverse()
    return out


def first_difference(a: dict[str, list], b: dict[str, list]) -> str:
    """Where two replays' messages first differ, by index ('' when they are the same): each side maps
    a stream to its ``(type name, fields)`` in order (replay-to-replay determinism, where no message
    may be inserted or deleted, so pairing by index is the point)."""
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key, []), b.get(key, [])
        for i, (p, q) in enumerate(zip(x, y)):
            if p != q:
                fields = sorted(k for k in set(p[1]) | set(q[1]) if p[1].get(k) != q[1].get(k))
                return f"{key} #{i}: " + ", ".join(f"{k} {p[1].get(k)!r} / {q[1].get(k)!r}" for k in fields[:3])
        if len(x) != len(y):
            return f"{key}: {len(x)} messages against {len(y)}"
    return ""
