"""What a recording's cuts make in a stream, for hil/compare_stream.py: the recorder starts and stops while the
drivers run, so a stream's first and last messages may hold part of an epoch (:func:`partial`, the cut note),
be made partly of input read before the cut (:func:`flowing_at_start`), come from input whose live output
the recording ended before (:func:`after_cut`), or be a replayed driver's start-up the live one had done before
(:func:`begun_after_start`, :func:`mux_decided_before`). The rules are in hil/compare.py's docstring."""

from __future__ import annotations

from u2sa_hw.messages import ABSENT

from u2sa_hw.hil.compare_values import Sample, Tolerances, values_equal
from u2sa_hw.hil.stream_align import Pair

SHOWN_FIELDS = 8


START_CUT_NS = 1_000_000_000   # how long after a flowing stream's start the live driver's state at the cut may show


def flowing_at_start(rec: list[Sample], recording_start_ns: int | None) -> bool:
    """True when *rec* was already flowing as the recording began: its first message came within two of its own
    periods (the median of its first intervals) of the recording's start, not after a driver's start-up."""
    if recording_start_ns is None or len(rec) < 3:
        return False
    gaps = sorted(b.t_ns - a.t_ns for a, b in zip(rec[:9], rec[1:10]))
    return rec[0].t_ns - recording_start_ns <= 2 * gaps[len(gaps) // 2]


def recorded_times(pairs: list[Pair], rec: list[Sample], end_ns: int) -> tuple[list[int], list[int]]:
    """For each step of *pairs*, the log time of its recorded message or of the recorded one before it (an
    insertion; the stream's first before any), and of the first recorded message after it (*end_ns* after the
    last): where an unpaired replayed message lies on the recording's clock. One pass each way."""
    before, after = [0] * len(pairs), [0] * len(pairs)
    t = rec[0].t_ns
    for k, q in enumerate(pairs):
        if q.rec is not None:
            t = rec[q.rec].t_ns
        before[k] = t
    t = end_ns
    for k in range(len(pairs) - 1, -1, -1):
        after[k] = t
        if pairs[k].rec is not None:
            t = rec[pairs[k].rec].t_ns
    return before, after


# How long before the recording's end input may have been read whose live output the recording does not hold
# (a serial driver publishes an epoch at its last sentence or at the silence after it: well under this)
TAIL_CUT_NS = 1_000_000_000


def after_cut(replayed: Sample, last_recorded: Sample, recording_end_ns: int | None) -> bool:
    """True for a replayed message made of input the live driver read after its stream's last recorded message
    and within TAIL_CUT_NS of the recording's end: its header time is that input's recorded time (a driver on a
    replay's device clock stamps its messages with it) and falls between the two. A replayed message stamped on
    the replaying machine's clock is later than the recording's end, so this never holds for it."""
    if recording_end_ns is None or replayed.stamp_ns is None or last_recorded.stamp_ns is None:
        return False
    return (last_recorded.stamp_ns < replayed.stamp_ns <= recording_end_ns
            and replayed.stamp_ns >= recording_end_ns - TAIL_CUT_NS)


def mux_decided_before(rec_mode: list[Sample]) -> bool:
    """True when an RC mux's recorded RC_MODE stream (*rec_mode*) begins with a decided mode: the recording began
    after the live mux had come out of "no signal"."""
    from u2sa_hw.drivers.rc_mux.pulse import MODE_NO_SIGNAL

    return bool(rec_mode) and rec_mode[0].fields.get("mode") not in (None, MODE_NO_SIGNAL)


def begun_after_start(rec: list[Sample]) -> bool:
    """True for a PWM output stream whose first recorded write already has the output enabled: a driver
    starts its outputs disabled (duty 0, then neutral) before it enables them, so the recording began
    after the live driver's start-up, which the replayed driver does again."""
    return bool(rec) and rec[0].type_name == "RawPwmWrite" and bool(rec[0].fields.get("enabled"))


def partial(a: Sample, b: Sample, names: list[str]) -> bool:
    """True when *a* and *b* differ only in which fields they hold (*names*: the differing fields): each
    is ``presence_vector`` or a field one of them leaves out, and at least one is such a field. Every
    field both hold is then equal: one message holds part of the other's epoch."""
    if a.type_name != b.type_name:
        return False
    held = [n for n in names if n != "presence_vector"]
    return bool(held) and all(a.fields.get(n) is ABSENT or b.fields.get(n) is ABSENT for n in held)


def rest_of_cut(pairs: list[Pair], k: int, cut_pairs: set[tuple[int, int]], rec: list[Sample],
                 rep: list[Sample], tol: Tolerances) -> bool:
    """True when the unpaired message ``pairs[k]`` is beside a partial pair at a cut and holds part of the
    same epoch: every field it holds is held, equal, by that pair's message on the other side."""
    p = pairs[k]
    for q in (pairs[k - 1] if k else None, pairs[k + 1] if k + 1 < len(pairs) else None):
        if q is None or q.rec is None or q.rep is None or (q.rec, q.rep) not in cut_pairs:
            continue
        mine, other = (rec[p.rec], rep[q.rep]) if p.kind == "deleted" else (rep[p.rep], rec[q.rec])  # type: ignore[index]
        if mine.type_name == other.type_name and all(
                other.fields.get(n) is not ABSENT and values_equal(v, other.fields.get(n), tol.of(n))
                for n, v in mine.fields.items() if v is not ABSENT and n != "presence_vector"):
            return True
    return False


def cut_note(a: Sample, b: Sample, index: int, *, start: bool, origin_ns: int) -> str:
    """The note for a partial message at a cut: which side holds which fields, and where the cut is."""
    only_rec = [n for n, v in a.fields.items() if v is not ABSENT and b.fields.get(n) is ABSENT]
    only_rep = [n for n, v in b.fields.items() if v is not ABSENT and a.fields.get(n) is ABSENT]

    def names(fields: list[str]) -> str:
        return ", ".join(fields[:SHOWN_FIELDS]) + (f" (+{len(fields) - SHOWN_FIELDS})" if len(fields) > SHOWN_FIELDS
                                                   else "")

    held = "; ".join(part for part in (f"only the recorded one holds {names(only_rec)}" if only_rec else "",
                                       f"only the replayed one holds {names(only_rep)}" if only_rep else "") if part)
    where = ("at the start of the stream: the recording begins inside the epoch or burst of input this message "
             "was made of (the live driver had read its first part before), or the live driver, held up as it "
             "started, read it in two parts with a gap the log cannot tell from a silence" if start else
             "at the end of the stream: the recording ends inside the epoch or burst of input this message was "
             "made of")
    return (f"cut: recorded #{index} at t={(a.t_ns - origin_ns) / 1e9:.3f} s and its replay hold part of one epoch each ({held}; every "
            f"field both hold is equal), {where}: a note, not a difference")
