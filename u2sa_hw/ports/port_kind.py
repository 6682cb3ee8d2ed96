"""``PortKind``: the small typed protocol every port kind implements, one per ``u2sa_hw/ports/<kind>/`` package.

A kind says what its addresses look like and how one is opened, real or mock (pyserial's
``urlhandler/protocol_<scheme>.py``, python-can's backends, gpiozero's pin factories with the
mock factory beside the real ones). :data:`u2sa_hw.ports.kinds.PORT_KINDS` registers every
kind in one table; :func:`u2sa_hw.ports.address.parse_address` parses with the kind's
grammar and :func:`u2sa_hw.ports.opener.open_port` opens through it. The parsed
:class:`~u2sa_hw.ports.address.DeviceAddress` travels down to the backend as it is: no kind
rebuilds it as a string, and nothing parses it twice.

A kind's module imports neither its port library nor its backends: ``open_real`` and
``open_mock`` import them when called, so parsing an address never loads python-can.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.tap import Tap


@runtime_checkable
class PortKind(Protocol):
    """One port kind: its address grammar, its real backend, its mock client, its probe and its replay device.

    ``name`` is the address kind (``DeviceAddress.kind``) and the real scheme; ``mock+`` + name
    the mock one. ``package`` is the ``u2sa_hw.ports`` package the kind lives in (the PCA9685 is
    a kind of the ``pwm`` package). ``params`` are the query parameters its addresses take,
    ``options`` the keyword options ``open_port`` passes on (None: any, for python-can's bus
    options). ``preload`` names the modules opening one imports (``opener.preload``). ``probe``
    names the module of its ``u2sa check --probe`` (``PROBE``, the probe's name;
    ``target_params(address, expect)``; ``probe(target, seconds)``), None for a kind without one.
    ``install`` names the module whose ``plan_device`` says what ``u2sa install`` makes of a real
    address of the kind (a udev rule, an interface's bitrate, a unit drop-in), None for nothing.
    ``replay`` names the kind's replay device factory as ``"module:callable"`` (:func:`load_part`;
    a string, so ``u2sa_hw`` never imports ``hil``): ``factory(dev, run_dir, *, service, fast, rigs)``
    makes the device that plays a log's ``RAW.<device>`` records back to the driver (docs/replay.md).
    """

    name: str
    package: str
    example: str
    mock_example: str
    real_backend: str
    mock_backend: str
    params: tuple[str, ...]
    options: tuple[str, ...] | None
    preload: tuple[str, ...]
    probe: str | None
    install: str | None
    replay: str

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """``(backend, location, numbers)`` of an address split into *parts*, else raise ``fail(problem)``."""

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
        """Open the real device at *address* (``address.mock`` is False) as *device*."""

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
        """Open the mock device at *address* (``address.mock`` is True) as *device*."""


def check_options(kind: PortKind, address: DeviceAddress, device: str, options: dict[str, Any]) -> None:
    """TypeError when *options* holds one that *kind* does not take (``kind.options``; None takes any)."""
    if kind.options is None:
        return
    extra = sorted(set(options) - set(kind.options))
    if extra:
        raise TypeError(f"{device}: open_port({address.kind}) takes {', '.join(kind.options) or 'no options'}, "
                        f"not {', '.join(extra)}")


def load_part(spec: str) -> Any:
    """The object a kind's ``"module:name"`` part names (its ``replay`` factory), imported only now.

    ValueError names the text and the form when it is not ``module:name``; ImportError and
    AttributeError surface as they are (a wrong table entry is a bug, never hidden).
    """
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"port kind part {spec!r}: expected 'module:name', e.g. "
                         "'u2sa_hw.hil.replay_devices:make_serial_device'")
    return getattr(importlib.import_module(module), name)
