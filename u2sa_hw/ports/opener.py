"""``open_port(address, *, device, tap=None, **options)``: the kind table picks the backend.

Like python-can's ``BACKENDS`` and pyserial's ``serial_for_url``, the kind of a device address
(:mod:`u2sa_hw.ports.address`) is looked up in :data:`u2sa_hw.ports.kinds.PORT_KINDS`, and the
kind opens the parsed address, real (``open_real``) or mock (``open_mock``); the kind imports
its backend only then, so a GPS service never imports python-can. ``serial+X`` addresses are
serial ones (pyserial picks X).

Options a kind takes (everything else about the device is in its address):

======== ==================================================================================
serial   ``timeout`` (read timeout, s)
can      any ``can.Bus`` keyword (added to the address's parameters)
i2c      none (a mock+i2c address may carry ``timeout=S``: the client's answer timeout)
gpio     ``inputs`` (line offsets), ``outputs`` (line -> initial value), ``edge``, ``bias``;
         each line must be one the address lists (when it lists any)
pwm      ``period_ns``
pca9685  ``period_ns``
======== ==================================================================================

Errors: :class:`~u2sa_hw.ports.address.AddressError` for a malformed address or a line the
address does not list (a config error), :class:`~u2sa_hw.ports.errors.PortUnavailable` when
the device cannot be opened (with the fix).
"""

from __future__ import annotations

import importlib
from typing import Any

from u2sa_hw.ports.address import DeviceAddress, parse_address
from u2sa_hw.ports.kinds import PORT_KINDS
from u2sa_hw.ports.tap import Tap


def preload(address: DeviceAddress) -> None:
    """Import what opening *address* will import, now (a missing library is left for the open to report).

    What opening a device imports beyond the kind: its backend and the library under it (python-can
    alone is some 160 modules; ``PortKind.preload``). A driver preloads when it sets up, before its
    READY=1 arms the watchdog; left to the first open, in the service's first loop turn, that import
    took over 2 s without a ping on a loaded machine and the launcher killed a healthy motor driver.
    """
    for module in PORT_KINDS[address.kind].preload:
        try:
            importlib.import_module(module)
        except ImportError:
            pass   # the open raises PortUnavailable naming the library and the fix


def open_port(address: DeviceAddress | str, *, device: str, tap: Tap | None = None, **options: Any) -> Any:
    """Open the device at *address* as *device* (its name in errors and taps); see the module docstring."""
    if isinstance(address, str):
        address = parse_address(address, device=device)
    kind = PORT_KINDS[address.kind]
    open_backend = kind.open_mock if address.mock else kind.open_real
    return open_backend(address, device=device, tap=tap, **options)
