"""Device address grammar: every scheme parses to its typed parts, bad text gives one line with the fix."""

from __future__ import annotations

import pytest

from u2sa_hw.ports.address import AddressError, make_address, parse_address

GOOD = [
    ("serial:///dev/u2sa/gps?baud=9600", "serial", False,
     {"serial_path": "/dev/u2sa/gps", "baud": 9600, "framing": "8N1", "usb_id": None, "is_serial_url": False}),
    ("serial:///dev/ttyUSB0?baud=4800&parity=e&bytesize=7&stopbits=2&usb=1546:01A7&serial=A1B2", "serial", False,
     {"baud": 4800, "framing": "7E2", "usb_id": ("1546", "01a7"), "usb_serial": "A1B2"}),
    ("serial+socket://localhost:7000?baud=19200", "serial", False,
     {"serial_path": "socket://localhost:7000", "is_serial_url": True, "baud": 19200}),
    ("mock+serial:///run/sim/gps", "serial", True, {"serial_path": "/run/sim/gps", "baud": 9600}),
    ("can://socketcan/can0?bitrate=500000", "can", False,
     {"can_interface": "socketcan", "can_channel": "can0", "bitrate": 500000, "udp_port": None, "bus_options": {}}),
    ("mock+can://udp_multicast/239.74.163.2?port=17270&receive_own_messages=true", "can", True,
     {"can_interface": "udp_multicast", "can_channel": "239.74.163.2", "bitrate": None, "udp_port": 17270,
      "bus_options": {"port": 17270, "receive_own_messages": True}}),
    ("i2c://1/0x68", "i2c", False, {"i2c_bus": 1, "chip_address": 0x68}),
    ("mock+i2c:///run/sim/i2c-1.sock/0x28", "i2c", True,
     {"i2c_bus": "mock:/run/sim/i2c-1.sock", "chip_address": 0x28, "i2c_timeout": None}),
    ("mock+i2c:///run/replay/i2c-imu.sock/0x68?timeout=60", "i2c", True,
     {"i2c_bus": "mock:/run/replay/i2c-imu.sock", "chip_address": 0x68, "i2c_timeout": 60.0}),
    ("mock+i2c:///run/replay/i2c-imu.sock/0x68?timeout=0.5", "i2c", True, {"i2c_timeout": 0.5, "i2c_paced": False}),
    ("mock+i2c:///run/replay/i2c-imu.sock/0x68?timeout=60&paced=true", "i2c", True,
     {"i2c_timeout": 60.0, "i2c_paced": True}),
    ("mock+i2c:///run/replay/i2c-imu.sock/0x68?paced=False", "i2c", True, {"i2c_paced": False}),
    ("gpio://gpiochip0/17,27", "gpio", False, {"gpio_chip": "/dev/gpiochip0", "lines": (17, 27)}),
    ("gpio:///dev/gpiochip1", "gpio", False, {"gpio_chip": "/dev/gpiochip1", "lines": ()}),
    ("mock+gpio:///run/sim/gpiochip0.sock/5,6,13", "gpio", True,
     {"gpio_chip": "mock:/run/sim/gpiochip0.sock", "lines": (5, 6, 13)}),
    ("pwm://pwmchip0/2", "pwm", False,
     {"pwm_chip": "/sys/class/pwm/pwmchip0", "pwm_channel": 2, "location": "/sys/class/pwm/pwmchip0"}),
    ("mock+pwm:///run/sim/pwmchip0/0", "pwm", True, {"pwm_chip": "/run/sim/pwmchip0", "pwm_channel": 0}),
    ("pca9685://1/0x40/3", "pca9685", False,
     {"i2c_bus": 1, "chip_address": 0x40, "pwm_channel": 3, "location": "1"}),
    ("mock+pca9685:///run/sim/i2c-1.sock/0x41/15", "pca9685", True,
     {"i2c_bus": "mock:/run/sim/i2c-1.sock", "chip_address": 0x41, "pwm_channel": 15,
      "location": "/run/sim/i2c-1.sock"}),
]


@pytest.mark.parametrize("text,kind,mock,parts", GOOD, ids=[g[0].split("?")[0] for g in GOOD])
def test_every_scheme_parses_to_its_parts(text: str, kind: str, mock: bool, parts: dict) -> None:
    address = parse_address(text, device="dev")
    assert (address.kind, address.mock, address.url) == (kind, mock, text)
    for name, value in parts.items():
        assert getattr(address, name) == value, name
    rebuilt = make_address(address.kind, address.location, address.numbers, params=address.params,
                           mock=address.mock, backend=address.backend)
    assert parse_address(rebuilt.url, device="dev") == rebuilt
    assert (rebuilt.kind, rebuilt.location, rebuilt.numbers, dict(rebuilt.params)) == \
        (address.kind, address.location, address.numbers, dict(address.params))


def test_a_part_of_another_kind_is_refused() -> None:
    with pytest.raises(AttributeError, match="serial"):
        parse_address("i2c://1/0x68", device="imu").baud


def test_with_params_changes_only_the_parameter() -> None:
    address = parse_address("serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7", device="gps")
    faster = address.with_params(baud=115200)
    assert (faster.serial_path, faster.baud, faster.usb_id) == ("/dev/u2sa/gps", 115200, ("1546", "01a7"))
    assert address.with_params(usb=None).usb_id is None


BAD = [
    ("/dev/ttyUSB0", "did you mean 'serial:///dev/ttyUSB0'"),
    ("seral:///dev/x", "unknown scheme 'seral' (did you mean 'serial'?)"),
    ("serial:///dev/x?bud=9600", "unknown parameter 'bud' (did you mean 'baud'?)"),
    ("serial:///dev/x?baud=9601", "baud 9601 is not a serial rate"),
    ("serial:///dev/x?parity=Q", "parity 'Q'"),
    ("serial:///dev/x?usb=12:34", "usb='12:34' must be VENDOR:PRODUCT"),
    ("serial://dev/x", "absolute device path"),
    ("mock+serial+socket://h:1", "only serial takes a pyserial scheme"),
    ("can://socketcan", "expected can://INTERFACE/CHANNEL"),
    ("can://socketcan/can0?bitrate=fast", "bitrate='fast' must be a whole number"),
    ("can://socketcan/can0?bitrat=500000", "unknown parameter 'bitrat' (did you mean 'bitrate'?)"),
    ("mock+can://udp_multicast/239.74.163.2?prot=17270", "unknown parameter 'prot' (did you mean 'port'?)"),
    ("mock+can://virtual/bus?receive_own_messages=yes", "receive_own_messages='yes' must be true or false"),
    ("i2c://1/0x99", "not a 7-bit device address"),
    ("i2c://one/0x68", "adapter number"),
    ("i2c://1/0x68?speed=4", "unknown parameter 'speed'"),
    ("mock+i2c:///run/x.sock/0x68?timout=60", "unknown parameter 'timout' (did you mean 'timeout'?)"),
    ("i2c://1/0x68?timeout=60", "timeout= is only for mock+i2c addresses"),
    ("mock+i2c:///run/x.sock/0x68?timeout=0", "timeout='0' must be a number of seconds > 0"),
    ("mock+i2c:///run/x.sock/0x68?timeout=-2", "timeout='-2' must be a number of seconds > 0"),
    ("mock+i2c:///run/x.sock/0x68?timeout=soon", "timeout='soon' must be a number of seconds > 0"),
    ("mock+i2c:///run/x.sock/0x68?timeout=nan", "timeout='nan' must be a number of seconds > 0"),
    ("mock+i2c:///run/x.sock/0x68?timeout=inf", "timeout='inf' must be a number of seconds > 0"),
    ("mock+i2c:///run/x.sock/0x68?timeout=", "timeout='' must be a number of seconds > 0"),
    ("mock+pca9685:///run/x.sock/0x40/3?timeout=60", "unknown parameter 'timeout'"),
    ("i2c://1/0x68?paced=true", "paced= is only for mock+i2c addresses"),
    ("mock+i2c:///run/x.sock/0x68?paced=1", "paced='1' must be true or false"),
    ("mock+i2c:///run/x.sock/0x68?pace=true", "unknown parameter 'pace' (did you mean 'paced'?)"),
    ("gpio://gpiochip0/1,x", "line numbers separated by commas"),
    ("gpio://gpiochip0/4,4", "repeats a line"),
    ("pwm:///tmp/x/0", "a real pwm chip lives under /sys/class/pwm"),
    ("pwm://pwmchip0/x", "not a channel number"),
    ("pca9685://1/0x40/16", "channel 16 is beyond the chip's 16 channels"),
    ("mock+pca9685://1/0x40/3", "a mock pca9685 address is"),
    ("/sys/class/pwm/pwmchip0", "did you mean 'pwm://pwmchip0/CHANNEL'"),
]


@pytest.mark.parametrize("text,problem", BAD, ids=[b[0] for b in BAD])
def test_bad_address_is_one_line_with_device_text_and_fix(text: str, problem: str) -> None:
    with pytest.raises(AddressError) as info:
        parse_address(text, device="gps")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"device 'gps': address {text!r}: ")
    assert problem in message
    assert "write it like " in message and "://" in info.value.fix


def test_non_string_address_is_an_address_error() -> None:
    with pytest.raises(AddressError, match="an address is a string, not int"):
        parse_address(9600, device="gps")  # type: ignore[arg-type]


@pytest.mark.parametrize("text", ["serial:///dev/x?baudd=9600", "can://socketcan/can0?bitrat=500000",
                                  "i2c://1/0x68?bus=2", "gpio://gpiochip0/17?bias=up", "pwm://pwmchip0/0?hz=50",
                                  "pca9685://1/0x40/3?freq=50", "mock+can://virtual/x?recieve_own_messages=true"])
def test_every_scheme_refuses_a_parameter_it_does_not_take(text: str) -> None:
    """A misspelt parameter is never handed on (a CAN one used to go to can.Bus, and install set no bitrate)."""
    with pytest.raises(AddressError, match=r"unknown parameter '\w+'.*addresses take: "):
        parse_address(text, device="dev")


def test_the_can_bus_options_an_address_may_carry_reach_can_bus_typed() -> None:
    address = parse_address("can://socketcan/can0?bitrate=500000&fd=true&data_bitrate=2000000&local_loopback=false",
                            device="wheels")
    assert address.bitrate == 500000
    assert address.bus_options == {"fd": True, "data_bitrate": 2000000, "local_loopback": False}


def test_a_mock_i2c_timeout_reaches_the_client_and_the_chips_beside_it(tmp_path) -> None:
    """timeout= is the mock client's answer timeout (a replay's bus holds data reads for its player); a
    chip opened beside it on the same bus (the AK8963 at 0x0c) keeps it; a real adapter takes none."""
    from u2sa_hw.mocks.i2c_bus import MockI2cBus
    from u2sa_hw.ports.i2c.port import MOCK_TIMEOUT_S, open_i2c
    from u2sa_hw.ports.opener import open_port

    address = parse_address(f"mock+i2c://{tmp_path}/b.sock/0x68?timeout=45", device="imu")
    beside = address.with_chip_address(0x0C)
    assert beside.i2c_timeout == 45.0 and beside.url.endswith("/0x0c?timeout=45")
    with MockI2cBus(socket_path=str(tmp_path / "b.sock")):
        with open_port(address, device="imu") as port, open_port(beside, device="mag") as mag, \
                open_port(address.with_params(timeout=None), device="imu2") as default:
            assert port._sock.gettimeout() == 45.0 and mag._sock.gettimeout() == 45.0
            assert default._sock.gettimeout() == MOCK_TIMEOUT_S == 2.0
    with pytest.raises(ValueError, match="for a mock bus and must be > 0 s"):
        open_i2c(device="imu", bus=1, address=0x68, timeout=5.0)
    with pytest.raises(ValueError, match="for a mock bus and must be > 0 s"):
        open_i2c(device="imu", bus=f"mock:{tmp_path}/b.sock", address=0x68, timeout=0.0)
