"""VESC CAN codecs against the worked frames of spec/devices/VESC_CAN.md."""

from __future__ import annotations

import pytest

from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.protocols.vesc_can import PacketId


def candump(msg) -> str:
    """An extended frame in candump notation (8 hex digit id), as the spec writes it."""
    return f"{msg.arbitration_id:08X}#{bytes(msg.data).hex().upper()}"


# ---- worked frames from the spec --------------------------------------------------------
def test_doc_example_set_current_51a_to_id_23() -> None:
    msg = vc.make_frame(23, PacketId.SET_CURRENT, vc.encode_set_current(51.0))
    assert candump(msg) == "00000117#0000C738"
    assert msg.is_extended_id
    assert vc.decode_command(PacketId.SET_CURRENT, msg.data) == 51.0


def test_set_rpm_negative() -> None:
    msg = vc.make_frame(5, PacketId.SET_RPM, vc.encode_set_rpm(-3000))
    assert candump(msg) == "00000305#FFFFF448"
    assert vc.decode_command(PacketId.SET_RPM, msg.data) == -3000.0


def test_set_duty_quarter() -> None:
    msg = vc.make_frame(5, PacketId.SET_DUTY, vc.encode_set_duty(0.25))
    assert candump(msg) == "00000005#000061A8"
    assert vc.decode_command(PacketId.SET_DUTY, msg.data) == 0.25


def test_status1() -> None:
    status = vc.Status1(erpm=12000, current_a=5.3, duty=0.456)
    msg = vc.make_frame(0x65, vc.status_packet_id(status), vc.encode_status(status))
    assert candump(msg) == "00000965#00002EE0003501C8"
    assert vc.decode_status(PacketId.STATUS, msg.data) == vc.Status1(12000.0, pytest.approx(5.3), pytest.approx(0.456))


def test_status4() -> None:
    status = vc.Status4(temp_fet_c=35.2, temp_motor_c=28.9, current_in_a=3.4, pid_pos_deg=90.0)
    msg = vc.make_frame(0x65, vc.status_packet_id(status), vc.encode_status(status))
    assert candump(msg) == "00001065#0160012100221194"
    decoded = vc.decode_status(PacketId.STATUS_4, msg.data)
    assert decoded == vc.Status4(pytest.approx(35.2), pytest.approx(28.9), pytest.approx(3.4), 90.0)


def test_status5() -> None:
    status = vc.Status5(tachometer=123456, voltage_in_v=48.2)
    msg = vc.make_frame(0x65, vc.status_packet_id(status), vc.encode_status(status))
    assert candump(msg) == "00001B65#0001E24001E20000"
    decoded = vc.decode_status(PacketId.STATUS_5, msg.data)
    assert decoded.tachometer == 123456 and isinstance(decoded.tachometer, int)
    assert decoded.voltage_in_v == pytest.approx(48.2)


def test_issue_715_ids_are_status_frames() -> None:
    assert vc.split_ext_id(0x917) == (PacketId.STATUS, 0x17)
    assert vc.split_ext_id(0x965) == (PacketId.STATUS, 0x65)


# ---- ids and tables ---------------------------------------------------------------------
def test_ext_id_layout_and_limits() -> None:
    assert vc.ext_id(PacketId.STATUS_6, 254) == 58 << 8 | 254
    assert vc.ext_id(PacketId.SET_DUTY, vc.BROADCAST_ID) == 0xFF
    with pytest.raises(vc.VescCanError, match="controller_id"):
        vc.ext_id(PacketId.SET_DUTY, 256)
    with pytest.raises(vc.VescCanError, match="bits 28..16"):
        vc.split_ext_id(0x10000)


def test_packet_ids_from_the_enum() -> None:
    assert PacketId.STATUS_5 == 27 and PacketId.STATUS_6 == 58 and PacketId.POLL_TS5700N8501_STATUS == 28
    assert PacketId.BMS_STATUS_5 == 68 and PacketId.PING == 17 and PacketId.PONG == 18
    assert vc.STATUS_NUMBER == {PacketId.STATUS: 1, PacketId.STATUS_2: 2, PacketId.STATUS_3: 3,
                                PacketId.STATUS_4: 4, PacketId.STATUS_5: 5, PacketId.STATUS_6: 6}
    assert vc.FaultCode.OVER_TEMP_FET == 5 and vc.FaultCode.RESOLVER_LOS == 22


@pytest.mark.parametrize("packet,value,raw", [
    (PacketId.SET_POS, 90.0, 90_000_000), (PacketId.SET_CURRENT_BRAKE, 2.5, 2500),
    (PacketId.SET_CURRENT_REL, -0.5, -50_000), (PacketId.SET_CURRENT_BRAKE_REL, 0.1, 10_000),
    (PacketId.SET_CURRENT_HANDBRAKE, 3.0, 3000), (PacketId.SET_CURRENT_HANDBRAKE_REL, 1.0, 100_000)])
def test_command_scales(packet: PacketId, value: float, raw: int) -> None:
    data = vc.encode_command(packet, value)
    assert int.from_bytes(data, "big", signed=True) == raw
    assert vc.decode_command(packet, data) == pytest.approx(value)


def test_encoders_round_where_the_firmware_truncates() -> None:
    assert int.from_bytes(vc.encode_set_duty(0.29), "big", signed=True) == 29000  # 0.29 * 1e5 = 28999.999...


def test_off_delay_form_reads_the_first_four_bytes() -> None:
    assert vc.decode_command(PacketId.SET_CURRENT, bytes.fromhex("0000C738") + b"\x03\xe8") == 51.0


@pytest.mark.parametrize("status", [
    vc.Status1(erpm=-250.0, current_a=-12.3, duty=-0.875), vc.Status2(amp_hours=1.2345, amp_hours_charged=0.5),
    vc.Status3(watt_hours=44.4, watt_hours_charged=2.0),
    vc.Status4(temp_fet_c=-5.5, temp_motor_c=80.0, current_in_a=-1.0, pid_pos_deg=359.98),
    vc.Status5(tachometer=-42, voltage_in_v=12.6), vc.Status6(adc1_v=3.3, adc2_v=0.0, adc3_v=1.25, ppm=-1.0)])
def test_status_round_trips(status: vc.StatusMessage) -> None:
    raw = vc.encode_status(status)
    assert len(raw) == vc.STATUS_DLC
    decoded = vc.decode_status(vc.status_packet_id(status), raw)
    assert type(decoded) is type(status)
    assert list(vars(decoded).values()) == pytest.approx(list(vars(status).values()), abs=0.02)


# ---- bad input ----------------------------------------------------------------------------
def test_truncated_and_unknown_payloads_raise_named_errors() -> None:
    with pytest.raises(vc.VescCanError, match=r"VESC STATUS_4: needs 8 data bytes, got 3 \(000102\)"):
        vc.decode_status(PacketId.STATUS_4, b"\x00\x01\x02")
    with pytest.raises(vc.VescCanError, match="VESC SET_DUTY: needs 4 data bytes, got 2"):
        vc.decode_command(PacketId.SET_DUTY, b"\x00\x01")
    with pytest.raises(vc.VescCanError, match="not a simple command"):
        vc.encode_command(PacketId.STATUS, 1.0)
    with pytest.raises(vc.VescCanError, match="not a STATUS message"):
        vc.decode_status(PacketId.SET_DUTY, bytes(8))
    with pytest.raises(vc.VescCanError, match="not a STATUS message"):
        vc.decode_status(200, bytes(8))


def test_values_that_do_not_fit_are_refused() -> None:
    with pytest.raises(vc.VescCanError, match="does not fit int16"):
        vc.encode_status(vc.Status4(temp_fet_c=4000.0, temp_motor_c=0, current_in_a=0, pid_pos_deg=0))
    with pytest.raises(vc.VescCanError, match="does not fit int32"):
        vc.encode_set_pos(5000.0)


# ---- COMM packets in CAN buffers --------------------------------------------------------------
def test_crc16_is_xmodem() -> None:
    assert vc.crc16(b"123456789") == 0x31C3  # the CRC-16/XMODEM check value
    assert vc.crc16(b"") == 0


def test_a_short_packet_is_one_process_short_buffer_frame() -> None:
    (frame,) = vc.buffer_frames(5, 254, bytes([vc.CommPacket.GET_APPCONF]))
    assert candump(frame) == "00000805#FE0011"   # PROCESS_SHORT_BUFFER to id 5: sender 254, send 0, COMM 17
    assert vc.BufferAssembler().feed(PacketId.PROCESS_SHORT_BUFFER, frame.data) == (254, 0, b"\x11")


def test_a_long_packet_uses_short_then_long_fill_frames_and_a_crc() -> None:
    payload = bytes(range(256)) + bytes(range(44))   # 300 bytes
    frames = vc.buffer_frames(7, 3, payload)
    packets = [vc.split_ext_id(f.arbitration_id) for f in frames]
    assert all(target == 7 for _, target in packets)
    fills = [p for p, _ in packets]
    # offsets 0, 7, .. 252 in FILL_RX_BUFFER (37 frames), then 259.. in FILL_RX_BUFFER_LONG, then PROCESS
    assert fills.count(PacketId.FILL_RX_BUFFER) == 37 and fills.count(PacketId.FILL_RX_BUFFER_LONG) == 7
    assert fills[-1] == PacketId.PROCESS_RX_BUFFER
    assert bytes(frames[37].data[:2]) == b"\x01\x03"   # u16 offset 259, big-endian
    assert bytes(frames[-1].data) == bytes([3, 0, 0x01, 0x2C]) + vc.crc16(payload).to_bytes(2, "big")
    assembler = vc.BufferAssembler()
    results = [assembler.feed(p, f.data) for (p, _), f in zip(packets, frames)]
    assert results[:-1] == [None] * (len(frames) - 1) and results[-1] == (3, 0, payload)

    lost = vc.BufferAssembler()   # a lost fill frame: the CRC says so, counted
    for (p, _), f in list(zip(packets, frames))[:10] + list(zip(packets, frames))[11:-1]:
        lost.feed(p, f.data)
    with pytest.raises(vc.VescCanError, match="CRC .* does not match"):
        lost.feed(PacketId.PROCESS_RX_BUFFER, frames[-1].data)
    assert lost.crc_errors == 1


def test_timeout_msec_is_read_and_replaced_in_the_app_configuration() -> None:
    appconf = bytes.fromhex("11223344") + bytes([9]) + (1000).to_bytes(4, "big") + bytes(20)
    assert vc.appconf_timeout_ms(appconf, controller_id=9) == 1000
    changed = vc.appconf_with_timeout(appconf, 300, controller_id=9)
    assert vc.appconf_timeout_ms(changed, controller_id=9) == 300
    assert changed[:5] == appconf[:5] and changed[9:] == appconf[9:] and len(changed) == len(appconf)
    with pytest.raises(vc.VescCanError, match="controller_id byte is 9, expected 4; unknown layout"):
        vc.appconf_timeout_ms(appconf, controller_id=4)
    with pytest.raises(vc.VescCanError, match="app configuration: needs 9 data bytes"):
        vc.appconf_timeout_ms(appconf[:6], controller_id=9)
