"""The CAN port kind: ``can://INTERFACE/CHANNEL`` (python-can), ``mock+can://`` (udp_multicast, virtual).

Options ``open_port`` passes on: any ``can.Bus`` keyword, over the address's own parameters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts
from u2sa_hw.ports.can.grammar import CAN_PARAMS, parse_can

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.can.port import CanPort
    from u2sa_hw.ports.tap import Tap


class CanKind:
    """CAN buses through python-can; the mock is one of python-can's own test buses, across processes."""

    name = "can"
    package = "u2sa_hw.ports.can"
    example = "can://socketcan/can0?bitrate=500000"
    mock_example = "mock+can://udp_multicast/239.74.163.2?port=17270"
    real_backend = "python-can interface/channel (socketcan on a vehicle)"
    mock_backend = "python-can udp_multicast/virtual bus with mock nodes"
    params = CAN_PARAMS
    options: tuple[str, ...] | None = None
    preload = ("u2sa_hw.ports.can.port", "can", "u2sa_hw.ports.can.clock")
    probe: str | None = "u2sa_hw.ports.can.probe"
    install: str | None = "u2sa_hw.ports.can.install"
    replay = "u2sa_hw.hil.replay_buses:make_can_device"   # a private stamped udp_multicast bus

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.can.grammar.parse_can`."""
        return parse_can(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> CanPort:
        """The python-can interface and channel (SocketCAN on a vehicle)."""
        return self._open(address, device=device, tap=tap, **options)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> CanPort:
        """A python-can test bus (udp_multicast across processes; ``clock=stamped``: a replay's device clock)."""
        return self._open(address, device=device, tap=tap, **options)

    def _open(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> CanPort:
        from u2sa_hw.ports.can.port import open_can

        bus_options = {**address.bus_options, **options}
        return open_can(device=device, interface=address.can_interface, channel=address.can_channel,
                        bitrate=address.bitrate, tap=tap, **bus_options)


CAN = CanKind()
