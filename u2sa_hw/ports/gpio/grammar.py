"""The GPIO address grammar: ``gpio://CHIP/LINE,LINE`` (CHIP under /dev), ``mock+gpio:///CHIP.sock/LINES``.
"""

from __future__ import annotations

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts

GPIO_PARAMS: tuple[str, ...] = ()


def parse_gpio(parts: UrlParts, fail: Fail) -> Parsed:
    """``gpio://CHIP/LINE,LINE`` (CHIP under /dev; mock: the chip socket path)."""
    full = (f"/dev/{parts.netloc}" if parts.netloc else "") + parts.path
    chip, _, last = full.rstrip("/").rpartition("/")
    numbers: tuple[int, ...] = ()
    if last and all(p.strip().isdigit() for p in last.split(",")):
        numbers = tuple(int(p) for p in last.split(","))
        if len(set(numbers)) != len(numbers):
            raise fail(f"line list {last!r} repeats a line")
    elif last and "," in last:
        raise fail(f"line list {last!r} must be line numbers separated by commas")
    else:
        chip = full.rstrip("/")
    if not chip or chip == "/dev":
        raise fail("expected gpio://CHIP/LINE,LINE (CHIP as gpiodetect names it)")
    if parts.mock and parts.netloc:
        raise fail("a mock gpio address is mock+gpio:///path/to/chip.sock/LINES")
    return ("mock" if parts.mock else "gpiod"), chip, numbers
