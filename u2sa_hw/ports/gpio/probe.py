"""The GPIO kind's probe (``u2sa check --probe``): the lines exist and no one holds them.

A kernel chip is read through libgpiod v2 (only on a vehicle), a mock chip through its ``info``
request (:mod:`u2sa_hw.ports.gpio.wire`). Nothing is requested or written.
"""

from __future__ import annotations

import errno
import json
import os
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

if TYPE_CHECKING:
    from u2sa_hw.check.targets import Target
    from u2sa_hw.ports.address import DeviceAddress

PROBE = "gpio"            # the probe's name (a target's ``port``)


def target_params(address: DeviceAddress, expect: Mapping[str, Any]) -> dict[str, Any]:
    """The chip and the lines of a GPIO *address*."""
    return {"chip": address.gpio_chip, "lines": list(address.lines)}


def _mockgpio_info(path: str) -> dict[str, Any]:
    from u2sa_hw.ports.gpio.wire import MOCK_JSON, MockFrameReader, encode_mock_json

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(3.0)
        sock.connect(path)
        sock.sendall(encode_mock_json({"op": "info", "id": 1}))
        reader = MockFrameReader()
        while True:
            data = sock.recv(65536)
            if not data:
                raise ConnectionError("the mock chip closed the connection")
            for kind, payload in reader.feed(data):
                if kind == MOCK_JSON:
                    return json.loads(payload)


def gpio_info(chip: str) -> tuple[int, dict[int, str]]:
    """``(number of lines, {line: consumer})`` of the lines in use on *chip*."""
    if chip.startswith("mock:"):
        info = _mockgpio_info(chip[len("mock:"):])
        used = {int(n): str(v.get("consumer", "?")) for n, v in info.get("lines", {}).items()}
        return int(info["num_lines"]), used
    path = chip if chip.startswith("/") else f"/dev/{chip}"
    if not Path(path).exists():   # said before gpiod is needed: the address is what is wrong
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
    import gpiod   # libgpiod v2, only on a vehicle

    with gpiod.Chip(path) as handle:
        count = handle.get_info().num_lines
        used = {}
        for line in range(count):
            info = handle.get_line_info(line)
            if info.used:
                used[line] = info.consumer or "?"
        return count, used


def probe(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    """The chip's lines exist and no one holds them."""
    chip = str(target.params["chip"])
    lines = [int(n) for n in target.params.get("lines", [])]
    try:
        count, used = gpio_info(chip)
    except ImportError:
        return False, "python gpiod (libgpiod v2) is not installed: pip install gpiod", {}
    except OSError as exc:
        return False, gpio_chip_problem(target, chip, exc), {}
    missing = [n for n in lines if not 0 <= n < count]
    busy = {n: used[n] for n in lines if n in used}
    parts = [f"{count} lines"]
    if missing:
        parts.append(f"line(s) {', '.join(map(str, missing))} do not exist (0..{count - 1})")
    if busy:
        parts.append("held: " + ", ".join(f"{n} by '{c}'" for n, c in busy.items()) + " (stop that service first)")
    if not missing and not busy:
        parts.append(f"line(s) {', '.join(map(str, lines)) or 'none'} exist and are free")
    return not missing and not busy, "; ".join(parts), {"lines": lines, "busy": busy}


def gpio_chip_problem(target: Target, chip: str, exc: OSError) -> str:
    """Why the chip of *target* cannot be looked at, with the fix (not a bare "No such file or directory")."""
    reason = exc.strerror or str(exc)
    lines = ",".join(str(n) for n in target.params.get("lines", [])) or "LINES"
    if chip.startswith("mock:"):
        return (f"device '{target.name}': no mock GPIO chip at {chip[len('mock:'):]} ({reason}); fix: start the "
                "mocks first (u2sa mock --vehicle ...) and probe the profile it writes, or correct the socket path")
    path = chip if chip.startswith("/") else f"/dev/{chip}"
    if isinstance(exc, PermissionError):
        return (f"device '{target.name}': cannot open GPIO chip {path} ({reason}); fix: run as a member of the gpio "
                "group (u2sa install adds the service user to it) or as root")
    return (f"device '{target.name}': no GPIO chip {path} ({reason}); fix: list the chips with gpiodetect and write "
            f"the right one in [devices.{target.name}] address, e.g. gpio://gpiochip0/{lines} (docs/ports.md), "
            "or enable the GPIO controller (its device-tree overlay)")
