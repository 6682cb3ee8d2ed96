"""What ``u2sa replay --compare`` compares: a stream's samples, the float tolerances, equality of values.

The rules are in hil/compare.py's docstring; this module holds the pieces every part of the
comparison uses (hil/compare_stream.py message by message, hil/compare_states.py over time,
hil/compare_report.py the report): :class:`Sample`, :class:`Tolerances`, :func:`values_equal`,
:func:`differing_fields`, and which channels and fields are compared in their own way
(``STATE_CHANNELS``, ``SYSTEM_FIELDS``, ``OUTPUT_RAW_TYPES``).
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

STATE_CHANNELS = ("RC_MODE", "MANUAL_CMD")         # published on a timer and on every change
# Fields a service decides from the whole system's state (the RC mux's pre-arm checks read every
# service's health), which a driver-level replay does not reproduce: a difference is a note.
SYSTEM_FIELDS: dict[str, tuple[str, ...]] = {
    "RC_MODE": ("autonomy_enabled", "armed", "hold", "blocked_by", "select_mismatch"),
}
# Fields a verdict change never changes: a message published for a verdict change has them as its neighbour does
# (an unpaired RC_MODE whose mode differs from both neighbours, a spurious "no signal", was published for the mode)
KEPT_BY_VERDICT: dict[str, tuple[str, ...]] = {"RC_MODE": ("mode",)}
OUTPUT_RAW_TYPES = ("RawGpioWrite", "RawPwmWrite")  # raw records of what a driver drives (compared)


@dataclass(frozen=True)
class Sample:
    """One message of a stream: log time, type and its comparable fields; *stamp_ns*: its header time (when the
    service published it, or for a driver on a replay's device clock the recorded time of its input)."""

    t_ns: int
    type_name: str
    fields: dict[str, Any]
    stamp_ns: int | None = None


class Tolerances:
    """Float tolerance per field: a default and ``glob -> tolerance`` overrides (first match wins).

    A file (``--tolerances FILE``, TOML) holds ``default = 1e-6``, a ``[fields]`` table of
    glob patterns (``"*sigma*" = 1e-3``, ``"x" = 0.01``) and ``ignore = ["psi_sigma"]``.
    """

    def __init__(self, default: float = 1e-6, fields: dict[str, float] | None = None,
                 ignore: tuple[str, ...] = ()) -> None:
        self.default = float(default)
        self.fields = dict(fields or {})
        self.ignore = tuple(ignore)
        self._cache: dict[str, float] = {}

    def of(self, name: str) -> float:
        """The tolerance of the field *name*."""
        tol = self._cache.get(name)
        if tol is None:
            tol = next((t for pattern, t in self.fields.items() if fnmatch.fnmatchcase(name, pattern)), self.default)
            self._cache[name] = tol
        return tol

    @classmethod
    def load(cls, path: Path | str, *, default: float = 1e-6, ignore: tuple[str, ...] = ()) -> "Tolerances":
        """Read a tolerance file; ValueError naming the file, the key and the fix when it is wrong."""
        import tomllib
        try:
            data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ValueError(f"{path}: cannot read the tolerance file: {exc.strerror or exc}") from None
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"{path}: not a TOML tolerance file ({exc}); "
                             'expected e.g. default = 1e-6, [fields] "x" = 0.01, ignore = ["psi_sigma"]') from None
        unknown = set(data) - {"default", "fields", "ignore"}
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; allowed: default, fields, ignore")

        def number(key: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{path}: {key} = {value!r}: a tolerance is a finite number >= 0")
            return float(value)

        fields = data.get("fields", {})
        if not isinstance(fields, dict):
            raise ValueError(f"{path}: fields must be a table of \"glob\" = tolerance")
        ignored = data.get("ignore", [])
        if not isinstance(ignored, list) or not all(isinstance(g, str) for g in ignored):
            raise ValueError(f"{path}: ignore must be a list of field globs")
        return cls(number("default", data.get("default", default)),
                   {str(k): number(f"fields.{k}", v) for k, v in fields.items()}, (*ignore, *ignored))


ToleranceLike = Union[float, Tolerances]


def as_tolerances(t: ToleranceLike) -> Tolerances:
    """*t* as :class:`Tolerances` (a number is the default tolerance of every field)."""
    return t if isinstance(t, Tolerances) else Tolerances(t)


def values_equal(a: Any, b: Any, tolerance: float) -> bool:
    """Floats within *tolerance* (NaN equals NaN), lists element-wise, the rest exactly."""
    if isinstance(a, float) or isinstance(b, float):
        try:
            fa, fb = float(a), float(b)
        except (TypeError, ValueError):
            return False
        if math.isnan(fa) or math.isnan(fb):
            return math.isnan(fa) and math.isnan(fb)
        return math.isclose(fa, fb, rel_tol=1e-9, abs_tol=tolerance)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(values_equal(x, y, tolerance) for x, y in zip(a, b))
    return a == b


def differing_fields(a: Sample, b: Sample, tolerance: ToleranceLike) -> list[str]:
    """Names of the fields that differ (``_type`` when the types do)."""
    if a.type_name != b.type_name:
        return ["_type"]
    tol = as_tolerances(tolerance)
    names = sorted(set(a.fields) | set(b.fields))
    return [n for n in names if not values_equal(a.fields.get(n), b.fields.get(n), tol.of(n))]
