"""The CAN address grammar: ``can://INTERFACE/CHANNEL`` (python-can), ``mock+can://udp_multicast/GROUP``.
"""

from __future__ import annotations

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts

# python-can bus options (can.Bus keyword arguments) an address may carry; bitrate is the interface's
# bit rate (SocketCAN: set by u2sa install at boot), port/hop_limit are udp_multicast's, the rest
# socketcan's and virtual's (python-can 4.x).
CAN_PARAMS = ("bitrate", "data_bitrate", "fd", "receive_own_messages", "local_loopback", "ignore_rx_error_frames",
              "port", "hop_limit", "rx_queue_size", "preserve_timestamps", "clock")
CAN_CLOCKS = ("stamped",)      # clock=stamped: a replay's frames carry their recorded bus time (mock+can only)
CAN_NUMBER_PARAMS = ("bitrate", "data_bitrate", "port", "hop_limit", "rx_queue_size")
CAN_FLAG_PARAMS = ("fd", "receive_own_messages", "local_loopback", "ignore_rx_error_frames", "preserve_timestamps")


def parse_can(parts: UrlParts, fail: Fail) -> Parsed:
    """``can://INTERFACE/CHANNEL``: backend the python-can interface, location the channel.

    ``clock=stamped`` (frames keep their senders' stamps: a replay's device clock) is taken only by
    ``mock+can://udp_multicast`` addresses, so a real bus can never set the time its driver sees.
    """
    if not parts.netloc or not parts.path.strip("/"):
        raise fail("expected can://INTERFACE/CHANNEL")
    for key in CAN_NUMBER_PARAMS:
        if key in parts.params and not parts.params[key].isdigit():
            raise fail(f"{key}={parts.params[key]!r} must be a whole number")
    for key in CAN_FLAG_PARAMS:
        if key in parts.params and parts.params[key].lower() not in ("true", "false"):
            raise fail(f"{key}={parts.params[key]!r} must be true or false")
    if "clock" in parts.params:
        if not parts.mock or parts.netloc != "udp_multicast":
            raise fail("clock= is only for mock+can://udp_multicast addresses (a replay's bus that sends "
                       "recorded stamps); a real CAN bus is timed by its kernel: remove clock=")
        if parts.params["clock"] not in CAN_CLOCKS:
            raise fail(f"clock={parts.params['clock']!r}: the one device clock is clock=stamped")
    return parts.netloc, parts.path.strip("/"), ()
