"""State streams (``RC_MODE``, ``MANUAL_CMD``) compared over time rather than message by message.

They are published on a timer as well as on every change, so which messages exist depends on
the timer's phase; see hil/compare.py's docstring for the rule.
"""

from __future__ import annotations

import bisect
from typing import Any

from u2sa_hw.hil.compare_stream import FieldDiff, StreamReport
from u2sa_hw.hil.compare_values import SYSTEM_FIELDS, Sample, ToleranceLike, Tolerances, as_tolerances, values_equal


def _missing_fields(s: Sample, times: list[int], others: list[Sample], *, window_ns: int,
                    tolerance: Tolerances) -> tuple[list[str], Sample | None]:
    """Fields of *s* whose value no message of *others* (sorted by time) had within *window_ns* of it,
    counting the one then held; and the nearest of those messages."""
    lo = bisect.bisect_left(times, s.t_ns - window_ns)
    hi = bisect.bisect_right(times, s.t_ns + window_ns)
    near = others[max(0, lo - 1):hi]
    if not near:
        return ["_type"], None
    nearest = min(near, key=lambda o: abs(o.t_ns - s.t_ns))
    missing = [] if any(o.type_name == s.type_name for o in near) else ["_type"]
    missing += [name for name, value in s.fields.items()
                if not any(values_equal(value, o.fields.get(name), tolerance.of(name)) for o in near)]
    return missing, nearest


def _elements(fields: dict[str, Any]) -> dict[str, Any]:
    """*fields* with every list split into its elements (``pulse_us[0]``, ...): each element is a state of its own."""
    out: dict[str, Any] = {}
    for name, value in fields.items():
        if isinstance(value, (list, tuple)):
            out[f"{name}.len"] = len(value)
            out.update((f"{name}[{i}]", v) for i, v in enumerate(value))
        else:
            out[name] = value
    return out


def compare_states(key: str, rec: list[Sample], rep: list[Sample], *, tolerance: ToleranceLike, edge: int,
                   time_tolerance_s: float, start_ns: int, end_ns: int, rate: float,
                   replay_start_ns: int) -> StreamReport:
    """Compare a state stream over time (see hil/compare.py's docstring)."""
    tol = as_tolerances(tolerance)
    rec = [Sample(s.t_ns, s.type_name, _elements(s.fields)) for s in rec]
    mapped = sorted((Sample(start_ns + int((s.t_ns - replay_start_ns) * rate), s.type_name, _elements(s.fields))
                     for s in rep), key=lambda s: s.t_ns)
    # only while the recorded stream ran: before it the recorded service was not up (or not recorded yet)
    first, last = (max(start_ns, rec[0].t_ns), min(end_ns, rec[-1].t_ns)) if rec else (start_ns, end_ns)
    inside = [s for s in mapped if first <= s.t_ns <= last]
    r = StreamReport(key, len(rec), len(inside))
    r.notes.append("a state stream: compared over time (every field value found on the other side within "
                   f"{time_tolerance_s:g} s), not message by message")
    if not rec or not inside:
        r.problems.append("only in the replay" if inside else "not reproduced by the replay")
        return r
    window = int(time_tolerance_s * 1e9)
    sides = ((rec, mapped, "recorded"), (inside, rec, "replayed"))
    unmatched = {"recorded": 0, "replayed": 0}
    at_edges = 0
    system = SYSTEM_FIELDS.get(key.split(" [", 1)[0], ())
    decided: dict[str, int] = {}
    for samples, others, side in sides:
        times = [o.t_ns for o in others]
        for i, s in enumerate(samples):
            missing, nearest = _missing_fields(s, times, others, window_ns=window, tolerance=tol)
            for name in [m for m in missing if m in system]:
                decided[name] = decided.get(name, 0) + 1
            missing = [m for m in missing if m not in system]
            if not missing:
                if side == "recorded":
                    r.matched += 1
                continue
            if i < edge or i >= len(samples) - edge:
                at_edges += 1
                continue
            unmatched[side] += 1
            for name in missing:
                d = r.fields.setdefault(name, FieldDiff(name))
                d.count += 1
                if d.first is None:
                    d.first_t_ns = s.t_ns
                    mine = s.type_name if name == "_type" else s.fields.get(name)
                    other = None if nearest is None else (nearest.type_name if name == "_type"
                                                          else nearest.fields.get(name))
                    d.first = (i, mine, other) if side == "recorded" else (i, other, mine)
    r.differing = unmatched["recorded"] + unmatched["replayed"]
    if r.differing:
        r.problems.append(f"{unmatched['recorded']} recorded and {unmatched['replayed']} replayed messages hold a "
                          f"field value the other side did not have within {time_tolerance_s:g} s")
    if at_edges:
        r.notes.append(f"{at_edges} message(s) at the start or end of the window without a counterpart "
                       "(the recording cuts the input there)")
    if decided:
        r.notes.append("decided from the whole system's health, which a driver-level replay does not reproduce "
                       f"(not a difference): {', '.join(f'{n} in {c}' for n, c in sorted(decided.items()))}")
    return r
