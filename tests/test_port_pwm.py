"""PWM port contract over every backend that runs here -- a sysfs-shaped directory (the mock
the simulation reads) and a PCA9685 on the mock I2C bus -- then the kernel's ordering rules,
and the dispatch of pca9685: addresses."""

from __future__ import annotations

import shutil
import sys
import tempfile
import threading
import types
from pathlib import Path
from typing import Iterator

import pytest

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw.ports import PortClosed, PortIOError, PortUnavailable, open_pwm
from u2sa_hw.ports.pwm.port import PwmChannel, SysfsPwmChannel, is_real_sysfs, make_sysfs_pwm_tree
from u2sa_hw.protocols import pca9685 as pca

SERVO_PERIOD = 20_000_000


class SysfsBackend:
    """A temp sysfs-shaped chip; the test observes the output through its files."""

    def __init__(self, root: Path) -> None:
        self.chip = make_sysfs_pwm_tree(root / "pwmchip0", npwm=4)
        self.address = str(self.chip)
        self.missing = str(root / "pwmchip9")
        self.period = SERVO_PERIOD  # the frame the backend runs for a requested SERVO_PERIOD

    def expect(self, duty_ns: int, enabled: bool) -> tuple[int, int, bool]:
        """What observe() shows once the channel holds *duty_ns* and *enabled*."""
        return self.period, duty_ns, enabled

    def observe(self, channel: int) -> tuple[int, int, bool] | None:
        path = self.chip / f"pwm{channel}"
        if not path.is_dir():
            return None
        read = lambda name: (path / name).read_text().strip()  # noqa: E731
        return int(read("period")), int(read("duty_cycle")), read("enable") == "1"

    def released(self, channel: int) -> bool:
        """Closed: unexported (the channel directory is gone)."""
        return self.observe(channel) is None

    def lose(self) -> None:
        shutil.rmtree(self.chip)

    def cleanup(self) -> None:
        pass


class Pca9685Backend:
    """A PCA9685 model at 0x40 on the mock I2C bus; the test observes the chip's LED registers."""

    def __init__(self, root: Path) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="pwmc", dir="/tmp"))  # Unix socket paths are short
        self.bus = MockI2cBus(socket_path=str(self._dir / "bus.sock"))
        self.pca: Pca9685Chip = self.bus.add(Pca9685Chip(address=0x40))  # type: ignore[assignment]
        self.bus.start()
        self.address = f"pca9685:{self.bus.address}:0x40"
        self.missing = f"pca9685:mock:{self._dir}/none.sock:0x40"
        self._prescale = pca.prescale_for_period(SERVO_PERIOD)
        self.period = pca.period_for_prescale(self._prescale)   # the nearest PRE_SCALE step

    def _ns(self, counts: int) -> int:
        return round(counts * pca.count_ns(self._prescale))

    def expect(self, duty_ns: int, enabled: bool) -> tuple[int, int, bool]:
        """The chip's output for *duty_ns*: whole counts of the frame, 0 when disabled."""
        counts = pca.counts_for_pulse(duty_ns, self._prescale) if enabled else 0
        return self.period, self._ns(counts), counts > 0

    def observe(self, channel: int) -> tuple[int, int, bool] | None:
        counts = self.pca.high_counts(channel)
        return round(self.pca.frame_period_us() * 1000), self._ns(counts), counts > 0

    def released(self, channel: int) -> bool:
        """Closed: the channel is full off (a PCA9685 channel has nothing to unexport)."""
        return self.pca.high_counts(channel) == 0

    def lose(self) -> None:
        self.bus.stop()

    def cleanup(self) -> None:
        self.bus.stop()
        shutil.rmtree(self._dir, ignore_errors=True)


@pytest.fixture(params=["sysfs", "pca9685"])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SysfsBackend | Pca9685Backend]:
    """Each PWM backend that runs on this machine: a sysfs-shaped chip and a PCA9685 on the mock I2C bus."""
    b = {"sysfs": SysfsBackend, "pca9685": Pca9685Backend}[request.param](tmp_path)
    yield b
    b.cleanup()


class TestPwmContract:
    """What every PWM backend must do."""

    def test_open_sets_the_period_and_leaves_the_output_off(self, backend) -> None:
        pwm = open_pwm(device="rudder", address=backend.address, channel=2)
        assert isinstance(pwm, PwmChannel)
        assert backend.observe(2) == backend.expect(0, False)
        pwm.close()

    def test_pulses_reach_the_output_and_are_tapped(self, backend) -> None:
        records: list = []
        pwm = open_pwm(device="rudder", address=backend.address, channel=1, tap=records.append)
        pwm.set_pulse_us(1500)
        pwm.enable(True)
        assert backend.observe(1) == backend.expect(1_500_000, True)
        pwm.set_pulse_ns(1_100_000)
        assert backend.observe(1) == backend.expect(1_100_000, True)
        pwm.close()
        states = [(r.device, r.channel, r.period_ns, r.duty_ns, r.enabled) for r in records]
        period = backend.period
        assert states == [
            ("rudder", 1, period, 0, False),
            ("rudder", 1, period, 1_500_000, False),
            ("rudder", 1, period, 1_500_000, True),
            ("rudder", 1, period, 1_100_000, True),
            ("rudder", 1, period, 1_100_000, False),  # close() stops the output
        ]

    def test_a_pulse_longer_than_the_period_is_refused(self, backend) -> None:
        records: list = []
        pwm = open_pwm(device="rudder", address=backend.address, channel=0, tap=records.append)
        with pytest.raises(ValueError, match="rudder"):
            pwm.set_pulse_ns(backend.period + 1)
        with pytest.raises(ValueError):
            pwm.set_pulse_us(-1)
        assert backend.observe(0) == backend.expect(0, False) and len(records) == 1
        pwm.close()

    def test_losing_the_chip_raises_port_closed(self, backend) -> None:
        pwm = open_pwm(device="rudder", address=backend.address, channel=0)
        pwm.set_pulse_us(1500)
        pwm.enable(True)
        backend.lose()
        with pytest.raises(PortClosed) as info:
            pwm.set_pulse_us(1200)
        assert info.value.device == "rudder" and info.value.fix
        # still gone: closed (sysfs), or unavailable where the backend tries to reopen its bus (PCA9685)
        with pytest.raises((PortClosed, PortUnavailable)) as again:
            pwm.set_pulse_us(1300)
        assert again.value.device == "rudder"
        pwm.close()  # closing a lost channel is fine

    def test_missing_chip_is_unavailable_with_a_fix(self, backend) -> None:
        with pytest.raises(PortUnavailable) as info:
            open_pwm(device="rudder", address=backend.missing, channel=0)
        assert info.value.device == "rudder" and info.value.address == backend.missing and info.value.fix

    def test_close_releases_the_channel_for_the_next_open(self, backend) -> None:
        pwm = open_pwm(device="rudder", address=backend.address, channel=3)
        pwm.set_pulse_us(1800)
        pwm.enable(True)
        pwm.close()
        assert backend.released(3)
        again = open_pwm(device="rudder", address=backend.address, channel=3)
        assert backend.observe(3) == backend.expect(0, False)
        again.close()


class TestSysfsSemantics:
    """The kernel's rules, which the mock enforces as the kernel would."""

    def test_export_creates_the_channel_files(self, tmp_path: Path) -> None:
        chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=8)
        assert (chip / "npwm").read_text().strip() == "8"
        pwm = open_pwm(device="esc", address=str(chip), channel=5)
        assert (chip / "export").read_text() == "5"
        assert sorted(p.name for p in (chip / "pwm5").iterdir()) == ["duty_cycle", "enable", "period", "polarity"]
        assert (chip / "pwm5" / "polarity").read_text().strip() == "normal"
        pwm.close()
        assert (chip / "unexport").read_text() == "5" and not (chip / "pwm5").exists()

    def test_period_changes_keep_duty_within_period(self, tmp_path: Path) -> None:
        chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0")
        pwm = open_pwm(device="esc", address=str(chip), channel=0)
        assert isinstance(pwm, SysfsPwmChannel)
        pwm.set_pulse_us(1500)
        # shrinking below the old duty: the duty must be written first, or EINVAL
        pwm.configure(period_ns=1_000_000, duty_ns=900_000)
        assert (chip / "pwm0" / "period").read_text().strip() == "1000000"
        # growing with a duty above the old period: the period must be written first
        pwm.configure(period_ns=20_000_000, duty_ns=15_000_000)
        assert (chip / "pwm0" / "duty_cycle").read_text().strip() == "15000000"
        pwm.set_period_ns(10_000_000)
        assert (pwm.period_ns, pwm.duty_ns) == (10_000_000, 10_000_000)
        pwm.close()

    def test_channel_beyond_npwm_is_unavailable(self, tmp_path: Path) -> None:
        chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
        with pytest.raises(PortUnavailable, match="channel 2 does not exist"):
            open_pwm(device="esc", address=str(chip), channel=2)

    def test_garbage_in_an_attribute_is_a_clear_error(self, tmp_path: Path) -> None:
        chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0")
        open_pwm(device="esc", address=str(chip), channel=0)  # exported, left in place
        (chip / "pwm0" / "duty_cycle").write_text("garbage\n")
        with pytest.raises(PortIOError, match="not a number") as info:
            open_pwm(device="esc", address=str(chip), channel=0)
        assert "esc" in str(info.value)

    def test_a_concurrent_reader_never_sees_a_half_written_file(self, tmp_path: Path) -> None:
        chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0")
        pwm = open_pwm(device="esc", address=str(chip), channel=0)
        bad: list[str] = []
        done = threading.Event()

        def simulation_reads() -> None:
            while not done.is_set():
                text = (chip / "pwm0" / "duty_cycle").read_text()
                if not text.strip().isdigit():
                    bad.append(text)

        reader = threading.Thread(target=simulation_reads)
        reader.start()
        for us in range(1000, 2000, 5):
            pwm.set_pulse_us(us)
        done.set()
        reader.join()
        pwm.close()
        assert bad == []

    def test_only_paths_in_sys_are_real_sysfs(self, tmp_path: Path) -> None:
        assert is_real_sysfs("/sys/class/pwm/pwmchip0")
        assert not is_real_sysfs(tmp_path / "pwmchip0")


def test_pca9685_addresses_go_to_the_pca9685_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[dict] = []
    backend = types.ModuleType("u2sa_hw.ports.pwm.pca9685")
    backend.open_pca9685_pwm = lambda **kwargs: calls.append(kwargs) or "pca-channel"  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "u2sa_hw.ports.pwm.pca9685", backend)
    got = open_pwm(device="rudder", address="pca9685:1:0x40", channel=7, period_ns=3_000_000)
    assert got == "pca-channel"
    assert calls == [dict(device="rudder", address="pca9685:1:0x40", channel=7, period_ns=3_000_000, tap=None)]
