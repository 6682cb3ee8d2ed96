"""Dropping impossible measurement values: counted per kind, logged once per kind.

A driver checks every value it is about to publish against the value's physical range
and the device's documented range (:func:`in_range`); a value outside it is not a
measurement -- a corrupted frame, a firmware fault, a checksum collision -- and is dropped
(never clamped: a clamped value looks real). :class:`ValueDrops` keeps the count per kind
(``"pitch"``, ``"wheel speed"``) for the service's health and logs the first drop of each
kind as a warning, so a device that keeps sending garbage fills neither the log nor the
estimator.
"""

from __future__ import annotations

import logging
import math
from typing import Any


def in_range(value: float | None, low: float, high: float) -> bool:
    """True when *value* is a finite number within ``[low, high]`` (None is not)."""
    return value is not None and math.isfinite(value) and low <= value <= high


class ValueDrops:
    """Counts of dropped values by kind (one warning per kind); *what* names them in health and the log."""

    def __init__(self, logger: logging.Logger, *, device: str, what: str = "out of range") -> None:
        self.logger = logger
        self.device = device
        self.what = what
        self.counts: dict[str, int] = {}

    def drop(self, kind: str, detail: str) -> None:
        """One value of *kind* was dropped; *detail* (the value and the range) goes into the first warning."""
        seen = self.counts.get(kind, 0)
        self.counts[kind] = seen + 1
        if not seen:
            self.logger.warning("%s: dropping %s %s values (counted in health; logged once per kind): %s",
                                self.device, self.what, kind, detail)

    def check(self, kind: str, value: float | None, low: float, high: float, *, unit: str = "") -> float | None:
        """*value* when it is within ``[low, high]``; None (counted as a drop of *kind*) when not.

        None stays None without a count: a value the device did not send is not a bad value.
        """
        if value is None:
            return None
        if in_range(value, low, high):
            return value
        self.drop(kind, f"{kind} {value!r}{unit} outside {low:g}..{high:g}{unit}")
        return None

    @property
    def total(self) -> int:
        """Values dropped, all kinds."""
        return sum(self.counts.values())

    def summary(self) -> str:
        """``kind:count`` pairs, comma separated, sorted by kind (``""`` when none)."""
        return ",".join(f"{kind}:{n}" for kind, n in sorted(self.counts.items()))

    def details(self, key: str) -> dict[str, Any]:
        """Health details ``<key>`` (the total) and ``<key>_kinds`` (the summary)."""
        return {key: self.total, f"{key}_kinds": self.summary()}
