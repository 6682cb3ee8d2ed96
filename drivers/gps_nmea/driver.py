"""GPS over serial NMEA 0183: a proprioceptive sensor publishing one State Information per fix.

Each line is parsed by pynmeagps (checksums enforced: a bad one is counted per sentence
kind and dropped; blank lines and AIS ``!AIVDM`` are ignored). Sentences are grouped into
epochs by their UTC times (``u2sa_hw.drivers.gps_nmea.epochs``), and each epoch becomes one message
(``u2sa_hw.drivers.gps_nmea.fix``): position about the profile origin in the configured
``position_frame``, NED ground velocity from speed and course, psi from HDT, sigmas from
GST or HDOP. Sentences that come after their epoch was published are merged into it and
only what they add is published (never the position twice). Values outside their
physical range are dropped, counted (``out_of_range``) and logged once per kind. No fix,
dead reckoning or simulator: no position and no velocity (an HDT heading still goes out),
status ``degraded`` with the reason. An epoch without a position sentence (a lone ZDA or
HDT) says nothing about the fix; the fix expires after ``stale_after_s`` without one.

See docs/drivers-serial.md for the config, frames and faults.
"""

from __future__ import annotations

import datetime as dt
import math
import time
from collections import Counter
from typing import Any

from pynmeagps.nmeatypes_get import NMEA_PAYLOADS_GET

from u2sa_hw.config.fields import field

from u2sa_hw.drivers.gps_nmea.epochs import GpsEpochCollector
from u2sa_hw.drivers.gps_nmea.fix import (ALTITUDE_DATUMS, GGA_QUALITY, POSITION_FRAMES, GpsFix, StateSettings, fix_from_epoch,
                             horizontal_sigma, state_from_fix)
from u2sa_hw.drivers.nmea_fields import BadChecksum, Epoch, SentenceError, parse_sentence
from u2sa_hw.drivers.serial_sensor import SerialLineSensor
from u2sa_hw.drivers.value_ranges import ValueDrops

MAX_MERGED_SENTENCES = 128   # an epoch with its supplements; beyond, a receiver is repeating itself
GPS_KINDS = frozenset({"GGA", "RMC", "GLL", "VTG", "GSA", "GST", "GNS", "ZDA", "HDT"})


class GpsNmeaDriver(SerialLineSensor):
    """A GNSS receiver speaking NMEA 0183 on a serial port (any talker: GP, GN, GL, GA, GB, GQ ...)."""

    MOCK_KINDS = ("nmea_gps",)

    CONFIG = (
        field("position_frame", "NED", "NED: x north, y east, z down (m) about the profile origin; "
                                       "GEODETIC: x = lat, y = lon (deg), z = altitude (m up) (any case)",
              choices=POSITION_FRAMES, case_insensitive=True),
        field("altitude_datum", "msl", "msl: the GGA altitude (above the geoid); ellipsoid: plus the geoid "
                                       "separation (any case)", choices=ALTITUDE_DATUMS, case_insensitive=True),
        field("uere_m", 3.0, "user equivalent range error (m): sigmas from HDOP/VDOP when there is no GST", gt=0, le=1000.0),
        field("speed_sigma_mps", 0.1, "sigma of x_dot, y_dot (m/s)", gt=0, le=100.0),
        field("heading_sigma_deg", 0.5, "sigma of psi from HDT (deg)", gt=0, le=180),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.epochs = GpsEpochCollector()
        self._epoch_mode = self.epochs.mode
        self.epoch_count = 0
        self.supplements = 0
        self.repeated_fixes = 0
        self._date: tuple[dt.date, dt.time] | None = None   # the latest date a sentence gave, and its time
        self._fix_key: tuple[object, ...] | None = None   # time and position of the latest fix published
        self.fix: GpsFix | None = None       # the latest epoch's reading that said something of the fix
        self.last_fix: GpsFix | None = None  # the latest epoch with a position
        self._fix_at: float | None = None    # monotonic time self.fix was read
        self._expiry_said = False                # the expiry of self.fix has been logged and published
        self._last_epoch: Epoch | None = None            # the latest epoch published (supplements merge into it)
        self._published: set[str] = set()                # the fields published for it
        self._rejects_counted: Counter[str] = Counter()  # its out-of-range values already counted in health
        self.talkers: set[str] = set()
        self.drops = ValueDrops(self.logger, device=name)
        self._data_said = ""   # the ``data`` detail as last published on a change ("" before any)

    def settings(self) -> StateSettings:
        """The config as the fix-to-message settings (read live, so changes apply at the next epoch)."""
        cfg = self.config
        return StateSettings(origin=self.profile.origin, position_frame=cfg.get("position_frame"),
                             altitude_datum=cfg.get("altitude_datum"), uere_m=cfg.get("uere_m"),
                             speed_sigma_mps=cfg.get("speed_sigma_mps"), heading_sigma_deg=cfg.get("heading_sigma_deg"))

    # -- lines and epochs -------------------------------------------------------------------
    def handle_line(self, line: bytes, received: float) -> None:
        """Parse one line; publish the previous epoch when this sentence starts a new one."""
        try:
            sentence = parse_sentence(line)
        except BadChecksum as exc:
            # a kind no receiver sends (line noise that kept its shape) is counted as "?": the counts stay few
            self.count_bad_checksum(exc.kind if exc.kind in NMEA_PAYLOADS_GET else "?", str(exc))
            done = self.epochs.dropped(exc.kind, exc.talker)
            if done is not None:
                self.publish_epoch(done)
            return
        except SentenceError as exc:
            self.count_malformed(str(exc))
            return
        if sentence is None or sentence.kind not in GPS_KINDS:
            self.ignored += 1
            return
        self.count_valid(noise_bytes=sentence.noise_bytes)
        self.talkers.add(sentence.talker)
        ended = self.epochs.add(sentence, received=received)
        if self.epochs.mode != self._epoch_mode:
            self._log_epoch_mode(sentence.kind)
        for done in ended:
            self.publish_epoch(done)

    def _log_epoch_mode(self, kind: str) -> None:
        """Say once how epochs end now (*kind*: the sentence that changed it)."""
        mode, self._epoch_mode = self.epochs.mode, self.epochs.mode
        if mode == "on completion" and self.epochs.expected is not None:
            expected = ",".join(f"{t}{k}x{n}" if n > 1 else f"{t}{k}"
                                for (t, k), n in sorted(self.epochs.expected.items()))
            self.logger.info("%s: epochs hold %s: each ends with its last sentence", self.name, expected)
        elif mode == "on time or silence":
            self.logger.info("%s: a %s came after its epoch looked complete: the receiver's epochs vary, so they "
                             "end on the next time or epoch_gap_s of silence from now on (the late sentence is "
                             "merged into its epoch)", self.name, kind or "sentence")

    def handle_idle(self) -> None:
        """The receiver finished its burst: publish the epoch."""
        done = self.epochs.flush()
        if self.epochs.mode != self._epoch_mode:
            self._log_epoch_mode("")
        if done is not None:
            self.publish_epoch(done)

    def on_port_lost(self) -> None:
        """A half-received epoch is dropped, and what a complete epoch holds is learned again."""
        self.epochs.reset()
        self._epoch_mode = self.epochs.mode
        self._last_epoch, self._published, self._fix_key = None, set(), None
        self._rejects_counted = Counter()

    def publish_epoch(self, epoch: Epoch) -> None:
        """Turn one epoch into at most one State Information and publish it.

        A supplement (sentences of an epoch already published) is merged into that epoch, and
        only the fields not yet published for it go out, stamped like the epoch."""
        last = self._last_epoch
        supplement = epoch.supplement and last is not None and last.time == epoch.time
        if supplement and last is not None:
            if len(last.sentences) >= MAX_MERGED_SENTENCES:
                return   # a receiver repeating one epoch's sentences without end: nothing new in them
            epoch = Epoch(received=last.received, time=last.time, sentences=last.sentences + epoch.sentences)
            self.supplements += 1
            already, counted = self._published, self._rejects_counted
        else:
            self.epoch_count += 1
            already, counted = set(), Counter()
        fix = fix_from_epoch(epoch)
        if not supplement and fix.has_fix and self._same_fix(fix):
            # The same time and position again (a receiver whose timestamp stopped advancing, gpsd's
            # "latch"): not a new measurement. It is not published again, and it does not keep the fix
            # alive: after stale_after_s of repeats the fix is lost (fail safe).
            self.repeated_fixes += 1
            return
        # the merged epoch's rejects hold its earlier sentences' again: count only the new ones, once each
        rejects = Counter(fix.rejects)
        for kind, n in (rejects - counted).items():
            for _ in range(n):
                self.drops.drop(kind, f"a {kind} value outside its physical range in {','.join(fix.kinds)}")
        self._rejects_counted = counted | rejects
        self._last_epoch = epoch
        self._carry_date(fix)
        if fix.reported:   # an epoch of ZDA or HDT alone says nothing of the fix
            self._take_fix(fix)
        if fix.has_fix:
            self._fix_key = (fix.utc_time, fix.lat, fix.lon)
        msg = state_from_fix(fix, self.settings())
        if msg is None:
            self._published = already
            return
        for name in msg.present_fields():
            if name in already or not math.isfinite(msg.get(name)):
                if name not in already and not self._rejects_counted[f"{name} not finite"]:
                    self._rejects_counted[f"{name} not finite"] = 1   # once per epoch, like the rejects
                    self.drops.drop(name, f"{name} = {msg.get(name)!r} is not finite")
                msg.clear(name)
        self._published = already | set(msg.present_fields())
        if msg.presence_vector:
            self.publish_measurement(msg, received=epoch.received)

    def _carry_date(self, fix: GpsFix) -> None:
        """Remember the latest date (ZDA, RMC); give it to an epoch without one (GGA alone), a day
        later when its time is earlier (past midnight). Only health shows the date."""
        if fix.utc_time is None:
            return
        if fix.utc_date is not None:
            self._date = (fix.utc_date, fix.utc_time)
        elif self._date is not None:
            date, time_of_day = self._date
            fix.utc_date = date if fix.utc_time >= time_of_day else date + dt.timedelta(days=1)

    def _same_fix(self, fix: GpsFix) -> bool:
        return self._fix_key == (fix.utc_time, fix.lat, fix.lon)

    def _take_fix(self, fix: GpsFix) -> None:
        """*fix* is the latest word on the fix: log and say a change at once."""
        old = self.current_fix()
        self.fix, self._fix_at, self._expiry_said = fix, time.monotonic(), False
        if fix.has_fix:
            self.last_fix = fix
        if (old is not None and old.has_fix) != fix.has_fix:
            self.logger.info("%s: %s", self.name, f"{fix.fix_name} fix" if fix.has_fix else f"lost the fix "
                             f"({fix.fix_name})")
        if old is None or fix.fix_rule != old.fix_rule or fix.fix_name != old.fix_name:
            # which rule gave the fix mode (docs/drivers-serial.md, "Fix mode"), once per change
            self.logger.debug("%s: %s by rule: %s", self.name, fix.fix_name, fix.fix_rule)
        if old is None or fix.fix_name != old.fix_name:
            # The pre-arm GPS check reads the fix type from health: say a change now, not at the next interval.
            self.publish_health()

    def current_fix(self) -> GpsFix | None:
        """The latest fix reading, or None when there is none or no position sentence came for
        ``stale_after_s`` (a receiver sending only ZDA or HDT has no fix to show: fail safe)."""
        at = self._fix_at
        if self.fix is None or at is None or time.monotonic() - at > self.config.get("stale_after_s"):
            return None
        return self.fix

    # -- health ----------------------------------------------------------------------------------
    def refresh_status(self) -> str:
        """The base status, and health published at once when the data goes stale or fresh again."""
        reason = super().refresh_status()
        age = self.data_age()
        data = "none yet" if age is None else ("stale" if age > self.config.get("stale_after_s") else "ok")
        if data != self._data_said:
            # The pre-arm GPS check reads ``data`` from health: say a change now, not at the next interval.
            # Set first: publish_health() comes back here through health_details().
            changed, self._data_said = bool(self._data_said), data
            if changed:
                self.publish_health()
        if self.fix is not None and self._fix_at is not None and self.current_fix() is None and not self._expiry_said:
            # the fix expired (no position sentence for stale_after_s): say it now, as a change of fix
            self._expiry_said = True
            self.logger.info("%s: lost the fix (no position sentence for %.1f s)", self.name,
                             self.config.get("stale_after_s"))
            self.publish_health()
        return reason

    def problem(self) -> str:
        """``"no fix"`` (or ``"dead reckoning"``, ``"simulator"``, ``"manual"``) while the latest
        epoch has no GNSS position; ``"no fix"`` too when position sentences stopped coming."""
        fix = self.current_fix()
        if fix is None:
            return "" if self.fix is None else "no fix"
        if fix.has_fix:
            return ""
        return {"DR": "dead reckoning"}.get(fix.fix_name, fix.fix_name)

    def sensor_details(self) -> dict[str, Any]:
        """Fix, quality, satellites, dilution and the latest position and motion."""
        fix, last = self.current_fix(), self.last_fix
        quality = fix.quality if fix else None
        details: dict[str, Any] = {
            "fix": bool(fix and fix.has_fix),
            "fix_type": fix.fix_name if fix else ("no fix" if self.fix is not None else "no data"),
            "fix_rule": fix.fix_rule if fix else ("no position sentence for stale_after_s"
                                                  if self.fix is not None else ""),
            "h_sigma_m": _show(horizontal_sigma(fix, self.config.get("uere_m")) if fix else None, ".2f"),
            "fix_quality": "" if quality is None else f"{quality} ({GGA_QUALITY.get(quality, 'unknown')})",
            "satellites": _show(fix.satellites if fix else None),
            "hdop": _show(fix.hdop if fix else None),
            "vdop": _show(fix.vdop if fix else None),
            "epochs": self.epoch_count,
            "epoch_end": self.epochs.mode,
            "late_sentences": self.epochs.late,
            "supplements": self.supplements,
            "repeated_fixes": self.repeated_fixes,
            **self.drops.details("out_of_range"),
            "talkers": ",".join(sorted(self.talkers)),
            "position_frame": self.config.get("position_frame"),
        }
        if last is not None:
            details.update({"lat": _show(last.lat, ".8f"), "lon": _show(last.lon, ".8f"),
                            "alt": _show(last.altitude(self.config.get("altitude_datum")), ".2f"),
                            "speed_mps": _show(last.speed_mps, ".3f"), "course_deg": _show(last.course_deg, ".2f"),
                            "geoid_sep_m": _show(last.geoid_sep, ".2f"), "geoid_source": last.geoid_source})
        if fix is not None:
            details["heading_deg"] = _show(fix.heading_deg, ".2f")
            details["utc"] = " ".join(str(v) for v in (fix.utc_date, fix.utc_time) if v is not None)
        return details


def _show(value: float | int | None, fmt: str = "") -> str:
    """A health detail value: empty when absent."""
    return "" if value is None else format(value, fmt)
