"""The GPIO port kind: ``gpio://CHIP/LINES`` (libgpiod v2 on ``/dev/CHIP``), ``mock+gpio:///CHIP.sock/LINES``.

Options ``open_port`` passes on: ``inputs`` (line offsets), ``outputs`` (line -> initial value),
``edge``, ``bias``; each line must be one the address lists, when it lists any (an
``AddressError``: a config error, never an open failure).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts
from u2sa_hw.ports.gpio.grammar import GPIO_PARAMS, parse_gpio
from u2sa_hw.ports.port_kind import check_options

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.gpio.port import GpioPort
    from u2sa_hw.ports.tap import Tap


class GpioKind:
    """Lines of a GPIO chip; the mock is a mock chip behind a Unix socket (:mod:`u2sa_hw.ports.gpio.wire`)."""

    name = "gpio"
    package = "u2sa_hw.ports.gpio"
    example = "gpio://gpiochip0/17,27"
    mock_example = "mock+gpio:///run/sim/gpiochip0.sock/5,6"
    real_backend = "libgpiod v2 on /dev/gpiochipN"
    mock_backend = "the mock GPIO chip's Unix socket"
    params = GPIO_PARAMS
    options: tuple[str, ...] | None = ("inputs", "outputs", "edge", "bias")
    preload = ("u2sa_hw.ports.gpio.port", "u2sa_hw.ports.gpio.mock_client", "u2sa_hw.ports.gpio.gpiod_backend")
    probe: str | None = "u2sa_hw.ports.gpio.probe"
    install: str | None = None   # udev/60-u2sa-permissions.rules covers every chip
    replay = "u2sa_hw.hil.replay_buses:make_gpio_device"   # a mock chip driving the recorded edges

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.gpio.grammar.parse_gpio`."""
        return parse_gpio(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> GpioPort:
        """The lines of the kernel chip (libgpiod v2)."""
        from u2sa_hw.ports.gpio.gpiod_backend import GpiodGpioPort

        request = self._request(address, device, options)
        return GpiodGpioPort(device=device, chip_path=address.location, tap=tap, **request)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> GpioPort:
        """The lines of the mock chip at the address's socket."""
        from u2sa_hw.ports.gpio.mock_client import MockGpioPort

        request = self._request(address, device, options)
        return MockGpioPort(device=device, socket_path=address.location, tap=tap, **request)

    def _request(self, address: DeviceAddress, device: str, options: dict[str, Any]) -> dict[str, Any]:
        """The checked line request: every line one the address lists (when it lists any)."""
        from u2sa_hw.ports.address import AddressError
        from u2sa_hw.ports.gpio.port import checked_request

        check_options(self, address, device, options)
        inputs = list(options.get("inputs", ()))
        outputs = dict(options.get("outputs") or {})
        if address.lines:
            missing = sorted((set(inputs) | set(outputs)) - set(address.lines))
            if missing:
                listed = ",".join(str(n) for n in sorted({*address.lines, *missing}))
                raise AddressError(device, address.url, f"line(s) {', '.join(map(str, missing))} are used but not "
                                   f"listed; list every line the device uses (…/{listed})", kind="gpio")
        edge, bias = options.get("edge", "both"), options.get("bias", "as-is")
        inputs, outputs = checked_request(device=device, inputs=inputs, outputs=outputs, edge=edge, bias=bias)
        return {"inputs": inputs, "outputs": outputs, "edge": edge, "bias": bias}


GPIO = GpioKind()
