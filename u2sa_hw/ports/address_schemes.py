"""The grammar every port kind shares: a device address split into parts, and the checks of its pieces.

:func:`u2sa_hw.ports.address.parse_address` splits ``scheme://body?query`` into
:class:`UrlParts` and hands them to the kind's parser (``PortKind.parse``, in
``u2sa_hw/ports/<kind>/grammar.py``); each returns ``(backend, location, numbers)`` or raises
the error its *fail* callback builds (an :class:`~u2sa_hw.ports.address.AddressError` naming
the device, the address and the fix).

Every kind takes a fixed set of query parameters (``PortKind.params``); any other is refused
with a did-you-mean (:func:`check_params`), so a typo such as ``bitrat=500000`` is an error,
not a value handed on silently.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

SYSFS_PWM = "/sys/class/pwm"
MOCK_PREFIX = "mock+"

Fail = Callable[[str], Exception]


@dataclass(frozen=True)
class UrlParts:
    """An address split by ``parse_address``: ``serial_scheme`` is the X of ``serial+X://`` ("" otherwise)."""

    kind: str
    mock: bool
    serial_scheme: str
    body: str                 # everything between ``://`` and ``?``
    netloc: str               # the body up to its first ``/``
    path: str                 # the rest of the body, with its leading ``/``
    params: Mapping[str, str]


Parsed = tuple[str, str, tuple[int, ...]]   # backend, location, numbers


def typed_option(text: str) -> Any:
    """A query value as can.Bus wants it: true/false, an int (any base), a float, else the text."""
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def number(text: str, what: str, fail: Fail) -> int:
    """*text* as an int (``0x40`` too), else *fail* naming *what*."""
    try:
        return int(text, 0)
    except ValueError:
        raise fail(f"{what} {text!r} is not a number") from None


def check_params(kind: str, allowed: tuple[str, ...], params: Mapping[str, str], fail: Fail) -> None:
    """Every query parameter is one of *allowed* (what *kind* takes); an unknown one fails with a did-you-mean."""
    for key in params:
        if key not in allowed:
            import difflib   # only for a misspelt option
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            known = ", ".join(allowed) if allowed else "none"
            raise fail(f"unknown parameter '{key}'{hint}; {kind} addresses take: {known}")


def chip_address(text: str, fail: Fail) -> int:
    """*text* as a 7-bit I2C chip address (0x03..0x77), else *fail*."""
    value = number(text, "I2C chip address", fail)
    if not 0x03 <= value <= 0x77:
        raise fail(f"I2C chip address {text} is not a 7-bit device address (0x03..0x77)")
    return value


def channel_number(text: str, fail: Fail, limit: int | None = None) -> int:
    """*text* as a channel number (below *limit* when given), else *fail*."""
    if not text.isdigit():
        raise fail(f"channel {text!r} is not a channel number")
    value = int(text)
    if limit is not None and value >= limit:
        raise fail(f"channel {value} is beyond the chip's {limit} channels (0..{limit - 1})")
    return value


def split_last(path: str, count: int, what: str, fail: Fail) -> tuple[str, list[str]]:
    """``/a/b.sock/0x40/3`` with count 2 -> ("/a/b.sock", ["0x40", "3"])."""
    parts = path.rstrip("/").split("/")
    if len(parts) < count + 2 or not all(parts[-count:]):   # leading "" of an absolute path + location
        raise fail(f"expected {what}")
    return "/".join(parts[:-count]), parts[-count:]


