"""``u2sa replay --compare``: the replayed outputs against the recorded ones, stream by stream.

A *stream* is one channel from one source service (``STATE_INFO [gps]``): only the
services the replay ran are compared, and never the contract channels (``U2SA_*``: health
carries uptime and CPU) or raw device I/O (``RAW.*``). For each stream:

- alignment (hil/stream_align.py): the two streams are paired as ``diff`` pairs lines, in
  order and by content, so one extra or missing message is one *insertion* or *deletion*
  (reported with its time in the recording) and the rest still pair. Paired messages
  *match* or *differ* in named fields. A stream of a service the recording has nothing
  from at all (it was not running) is shown as ``new``, with nothing to compare. A
  recording cuts its devices' input at both ends (the recorder starts and stops while
  drivers run), so insertions or deletions among the first or last ``edge`` messages of a
  stream are notes; elsewhere they are differences. So is a *partial* message there: a pair
  among the first or last ``edge`` whose only differences are fields one side holds and the
  other does not (``presence_vector`` with them), every field both hold being equal. That is
  what a cut epoch gives (the recording begins after the live driver read a burst's first
  sentences: the live fix holds position and velocity, the replayed one only the velocity of
  the sentences recorded; or it ends before the burst's last ones): a note naming the stream,
  the message and the cut, never counted as matched or different. A value that differs, at an
  edge or anywhere, and a partial message away from the edges, are differences.
  At the end, a replayed message after the last pair whose header time (a driver on the replay's
  device clock stamps it with its input's recorded time) lies after the stream's last recorded
  message and in the recording's last second was made of input whose live output the recording
  ended before: a note too (``after_cut``). An unpaired message of a run of equal messages (sticks
  held still) may be any of the run's - the alignment names the run's last - so the held-up
  windows and verdict changes below are judged over its whole run. A stream already flowing as the
  recording began (``flowing_at_start``) may show the live driver's state at the cut for a second:
  what differs within it is a note. An RC mux whose first recorded RC_MODE
  is decided (``mux_decided_before``): its replayed start-up before it decides is a note.
- fields: every field from ``enumerate_fields`` except the header's ``timestamp_us`` and
  ``sequence`` (and ``ignore`` patterns), floats equal within their field's tolerance
  (:class:`Tolerances`: a default and per-field globs, from ``--tolerances FILE``; absolute, or
  relative 1e-9), everything else exactly.
- timing: each message's time since the stream's first, replayed (times the rate) against
  recorded; the median and largest offset are shown and a largest offset above
  ``time_tolerance_s`` is a difference. Not checked for ``--fast`` replays, which have no clock.
  Messages a replayed service published before the playback began (while it started) are
  not timed: the first message at or after the playback's start is the reference.

Raw device I/O is left out except the records of what a driver *drives*: ``RawGpioWrite``
and ``RawPwmWrite`` (a GPIO or PWM driver's outputs), compared like any stream under
``RAW.<device> [service]``.

State channels (``STATE_CHANNELS``: ``RC_MODE``, ``MANUAL_CMD``) are published on a timer as well as on
every change, so which messages exist depends on the timer's phase. With a clock (``--rate``)
they are compared as states over time (hil/compare_states.py): each replayed message's time is mapped onto the
log's clock (the playback started at log time ``start_ns``), and every field value (each
element of a list on its own) of every message must also be found on the other side within
``time_tolerance_s`` of it (the state then held counts). The first and last ``edge``
messages of each side may miss (the input starts and ends there); they are notes. Replayed
messages from before the recorded stream's first message or after its last are not compared
(the recorded service was not running, or not recorded, then; after the input ends a driver
reacts to its end).

``SYSTEM_FIELDS`` are what a service decides from the rest of the system, not from its
device: the RC mux's ``autonomy_enabled``, ``armed``, ``hold``, ``blocked_by`` (its pre-arm
checks read every service's health) and ``select_mismatch`` (the recorded select read-back
against the replay's own enable decision). They are compared, and a difference is a note.
They do not steer the alignment, and a message on one side only that was published for a
change of one of them (one differs between it and the stream's message before or after it)
is a note too: on a loaded machine the live mux read the other services' health in another
order than the recorder wrote it, so its verdict may change a few messages apart from the
replay's. A timed or device-driven message away from a verdict change still counts.
"""

from __future__ import annotations

import fnmatch
from pathlib import Path
from typing import Any, Mapping, Sequence

from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY, MalformedMessage, enumerate_fields
from u2sa_hw.recording.log_reader import LogFile

from u2sa_hw.hil.compare_report import CompareReport
from u2sa_hw.hil.compare_states import compare_states
from u2sa_hw.hil.compare_cuts import begun_after_start, flowing_at_start, mux_decided_before
from u2sa_hw.hil.compare_stream import compare_stream
from u2sa_hw.hil.compare_values import OUTPUT_RAW_TYPES, STATE_CHANNELS, Sample, ToleranceLike, as_tolerances
from u2sa_hw.hil.held_up import HeldWindow
from u2sa_hw.hil.player import header_source

HEADER_FIELDS = ("*header.timestamp_us", "*header.sequence")


def load_streams(path: Path | str, *, sources: set[str], start_ns: int | None = None, end_ns: int | None = None,
                 ignore: tuple[str, ...] = ()) -> dict[str, list[Sample]]:
    """``"CHANNEL [source]"`` -> samples, for messages from *sources* within the window."""
    return _load_streams(path, sources=sources, start_ns=start_ns, end_ns=end_ns, ignore=ignore)[0]


def _load_streams(path: Path | str, *, sources: set[str], start_ns: int | None, end_ns: int | None,
                  ignore: tuple[str, ...]) -> tuple[dict[str, list[Sample]], int | None]:
    """:func:`load_streams` and the log's first log time, of any message (None for an empty log)."""
    patterns = (*HEADER_FIELDS, *ignore)
    streams: dict[str, list[Sample]] = {}
    first: int | None = None
    for m in LogFile(path).messages():
        first = m.log_time_ns if first is None else min(first, m.log_time_ns)
        if m.channel.startswith("U2SA_") or (m.channel.startswith("RAW.") and m.type_name not in OUTPUT_RAW_TYPES):
            continue
        if (start_ns is not None and m.log_time_ns < start_ns) or (end_ns is not None and m.log_time_ns > end_ns):
            continue
        try:
            msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
        except MalformedMessage:
            continue
        source = header_source(msg)
        if source not in sources:
            continue
        every = dict(enumerate_fields(msg))
        fields = {k: v for k, v in every.items() if not any(fnmatch.fnmatchcase(k, p) for p in patterns)}
        stamp_us = next((v for k, v in every.items() if k.endswith("header.timestamp_us")), 0)
        streams.setdefault(f"{m.channel} [{source}]", []).append(
            Sample(m.log_time_ns, type(msg).__name__, fields, int(stamp_us) * 1000 if stamp_us else None))
    return streams, first


def source(key: str) -> str:
    """The source service of a stream key (``"STATE_INFO [gps]"`` -> ``gps``)."""
    return key.rsplit(" [", 1)[1][:-1]


def compare_logs(recorded: Path | str, replayed: Path | str, *, services: set[str], start_ns: int | None = None,
                 end_ns: int | None = None, rate: float | None = 1.0, tolerance: ToleranceLike = 1e-6, edge: int = 1,
                 time_tolerance_s: float = 0.5, ignore: tuple[str, ...] = (),
                 replay_start_ns: int | None = None, pilot: Any = None,
                 held: Mapping[str, Sequence[HeldWindow]] | None = None) -> CompareReport:
    """Compare the streams of *services* in *recorded* (within the window) and *replayed*; ``rate=None``: no timing.

    *replay_start_ns*: the wall-clock time the playback began (log time *start_ns* was played
    then); with a rate and the window it lets state channels be compared over time.
    *pilot*: the check of the recorded pilot messages (u2sa_hw.recording.pilot_check.PilotCheck,
    ``ReplayResult.pilot``): reported, and a message that fails it is a finding.
    The recorded pilot trailers never reach the comparison (the log reader cuts them off).
    *held*: service -> the windows where the recording machine held it up
    (u2sa_hw.hil.held_up, ``ReplayPlan.held_windows``); what differs there is a note.
    """
    tol = as_tolerances(tolerance)
    ignore = (*ignore, *tol.ignore)
    rec, log_start = _load_streams(recorded, sources=services, start_ns=start_ns, end_ns=end_ns, ignore=ignore)
    rep = load_streams(replayed, sources=services, ignore=ignore)
    origin = start_ns if start_ns is not None else min((v[0].t_ns for v in rec.values() if v), default=0)
    # where the recording began, for flowing_at_start: the window's start, or the log's first message of any
    # channel (as a replay's plan takes it) - not the first compared message, which would make that stream
    # "flowing" whatever came before it
    began = start_ns if start_ns is not None else log_start
    recording_end = max((v[-1].t_ns for v in rec.values() if v), default=None)
    windows = held or {}
    # the RC muxes whose recording began after they had decided their mode (their first RC_MODE says so)
    decided = {source(key) for key, samples in rec.items() if key.startswith("RC_MODE [") and mux_decided_before(samples)}
    reports = []
    for key in sorted(set(rec) | set(rep)):
        a, b = rec.get(key, []), rep.get(key, [])
        timed = rate is not None and replay_start_ns is not None and start_ns is not None and end_ns is not None
        if timed and key.split(" [", 1)[0] in STATE_CHANNELS:
            reports.append(compare_states(key, a, b, tolerance=tol, edge=edge, time_tolerance_s=time_tolerance_s,
                                          start_ns=start_ns, end_ns=end_ns, rate=rate, replay_start_ns=replay_start_ns))
        else:
            reports.append(compare_stream(key, a, b, tolerance=tol, edge=edge, rate=rate,
                                          time_tolerance_s=time_tolerance_s, replay_start_ns=replay_start_ns,
                                          origin_ns=origin, held=windows.get(source(key), ()),
                                          started_before=begun_after_start(a), recording_end_ns=recording_end,
                                          decided_before=source(key) in decided,
                                          flowing=flowing_at_start(a, began)))
    recorded_sources = {source(key) for key in rec}
    for r in reports:
        if not r.recorded and source(r.key) not in recorded_sources:
            # a service that was not running (or not recorded) in the log: nothing to compare with
            r.problems.clear()
            r.notes.append("the recording has nothing from this service to compare with")
    return CompareReport(Path(recorded), Path(replayed), reports, tol, rate is not None, origin, pilot)
