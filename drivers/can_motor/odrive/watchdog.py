"""Turning on each ODrive axis's own watchdog over CAN and reading it back (for OdriveCanMotor).

The ODrive watchdog (``axis.config.enable_watchdog``/``watchdog_timeout``) disarms the axis
with WATCHDOG_TIMER_EXPIRED when no CAN frame reaches it for ``hw_watchdog_timeout_s``: the
last line of defence when the driver's process dies or hangs. Firmware 0.6 has endpoint access
over CAN (RxSdo/TxSdo), but endpoint ids belong to one firmware build (its flat_endpoints.json):
with ``watchdog_timeout_endpoint``/``enable_watchdog_endpoint`` and the build they belong to
(``endpoints_fw``, checked against Get_Version) the driver writes both and reads them back.
Firmware 0.5 has no parameter access over CAN at all: the watchdog must be set once with
odrivetool, and the driver says so (log and the ``hw_watchdog`` health detail).

``OdriveWatchdogSetup`` does this for every axis of one driver: ``step`` (called each tick
until the axis's ``WatchdogStep`` is settled) decides what can be done, asks again or gives up;
``on_version`` and ``on_tx_sdo`` take the node's answers. The driver arms an axis only once its
watchdog step is settled (at the latest after ``WD_TRIES * WD_REPLY_S``).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import can   # python-can loads when the port opens (u2sa_hw/ports/can/port.py)

from u2sa_hw.config.configurator import Configurator
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import Cmd

from u2sa_hw.drivers.can_motor.odrive.axis import OdriveAxis

WD_REPLY_S = 0.5  # wait this long for Get_Version / TxSdo answers before asking again
WD_TRIES = 4  # then the watchdog step is an error, and arming goes ahead without it
# config fields whose change starts every axis's watchdog set-up again
WATCHDOG_FIELDS = frozenset({"hw_watchdog", "hw_watchdog_timeout_s", "watchdog_timeout_endpoint",
                             "enable_watchdog_endpoint", "endpoints_fw", "firmware", "command_period_s"})


class OdriveWatchdogSetup:
    """Sets up and reads back the axis watchdogs of one ODrive driver, one step at a time.

    *config* is the driver's configuration (read at every step, so a change applies at once),
    *send* puts a frame on its bus, *label* names an axis in messages, *report_error* records
    an error for health and *logger* takes the rest.
    """

    def __init__(self, *, config: Configurator, send: Callable[[can.Message], bool],
                 label: Callable[[OdriveAxis], str], report_error: Callable[[str], None],
                 logger: logging.Logger) -> None:
        self.config = config
        self._send = send
        self._label = label
        self._report_error = report_error
        self.logger = logger

    def step(self, axis: OdriveAxis, now: float, *, firmware: str) -> None:
        """Move the watchdog set-up of *axis* on: decide what can be done, ask again, or give up."""
        cfg, wd, label = self.config, axis.wd, self._label(axis)
        timeout = float(cfg.get("hw_watchdog_timeout_s"))
        if wd.started is None:
            wd.started = now
        if not cfg.get("hw_watchdog"):
            wd.settle("off", "off (hw_watchdog = false): a dead driver leaves the axis at its last setpoint")
            self.logger.warning("%s: hw_watchdog is off; the axis keeps its setpoint if this driver dies", label)
            return
        if firmware == "0.5":
            wd.settle("unverified", f"not settable over CAN on fw 0.5: configure with odrivetool "
                                    f"(axis.config.watchdog_timeout = {timeout:g}, axis.config.enable_watchdog = "
                                    "True, save_configuration()); not readable over CAN either")
            self.logger.warning("%s: %s", label, wd.text)
            return
        endpoints = (cfg.get("watchdog_timeout_endpoint"), cfg.get("enable_watchdog_endpoint"))
        if not all(endpoints):
            wd.settle("unverified", "not set: endpoint ids unknown; set watchdog_timeout_endpoint, "
                                    "enable_watchdog_endpoint and endpoints_fw from the flat_endpoints.json of the "
                                    "node's firmware, or configure with odrivetool and save_configuration()")
            self.logger.warning("%s: watchdog %s", label, wd.text)
            return
        if now < wd.next_try:
            return
        if wd.tries >= WD_TRIES:
            asked = "Get_Version" if wd.version is None else "RxSdo reads"
            wd.settle("error", f"no answer to {asked} after {wd.tries} tries; the watchdog is not verified "
                               "(configure it with odrivetool if this firmware has no endpoint access)")
            self._report_error(f"{label}: watchdog {wd.text}")
            return
        wd.tries += 1
        wd.next_try = now + WD_REPLY_S
        if wd.version is None:
            self._send(cs.make_request(axis.spec.can_id, Cmd.GET_VERSION))
        else:
            self._write(axis)

    def on_version(self, axis: OdriveAxis, version: cs.Version, now: float) -> None:
        """A Get_Version reply: write the watchdog if the endpoint ids are for this build, else give up."""
        wd, cfg = axis.wd, self.config
        if wd.settled or wd.version is not None or wd.started is None:
            return
        wd.version = cs.version_text(version)
        if wd.version != cfg.get("endpoints_fw"):
            wd.settle("error", f"not set: the node runs firmware {wd.version} but the endpoint ids are for "
                               f"{cfg.get('endpoints_fw') or '(endpoints_fw empty)'}; take watchdog_timeout_endpoint "
                               f"and enable_watchdog_endpoint from the flat_endpoints.json of {wd.version} and set "
                               f"endpoints_fw = '{wd.version}'")
            self._report_error(f"{self._label(axis)}: watchdog {wd.text}")
            return
        wd.tries, wd.next_try = 1, now + WD_REPLY_S
        self._write(axis)

    def on_tx_sdo(self, axis: OdriveAxis, endpoint: int, raw: bytes) -> None:
        """A TxSdo reply: once both endpoints are read back, the watchdog is on or an error."""
        wd, cfg = axis.wd, self.config
        timeout_ep, enable_ep = cfg.get("watchdog_timeout_endpoint"), cfg.get("enable_watchdog_endpoint")
        if wd.settled or endpoint not in (timeout_ep, enable_ep):
            return
        wd.read[endpoint] = raw
        if len(wd.read) < 2:
            return
        wanted = float(cfg.get("hw_watchdog_timeout_s"))
        timeout = float(cs.sdo_value("float", wd.read[timeout_ep]))
        enabled = bool(cs.sdo_value("bool", wd.read[enable_ep]))
        if enabled and abs(timeout - wanted) < 1e-4:
            wd.settle("on", f"on {timeout:.2f} s (read back)")
            self.logger.info("%s: watchdog %s", self._label(axis), wd.text)
            return
        wd.settle("error", f"read back timeout {timeout:g} s, enabled {enabled} after writing {wanted:g} s, "
                           f"enabled True: endpoints {timeout_ep}/{enable_ep} may not be axis0.config."
                           f"watchdog_timeout/enable_watchdog of firmware {wd.version}; check them in its "
                           "flat_endpoints.json, or configure with odrivetool")
        self._report_error(f"{self._label(axis)}: watchdog {wd.text}")

    def _write(self, axis: OdriveAxis) -> None:
        cfg = self.config
        timeout_ep, enable_ep = cfg.get("watchdog_timeout_endpoint"), cfg.get("enable_watchdog_endpoint")
        axis.wd.read.clear()
        # timeout first, so the watchdog never runs with the firmware's default timeout
        self._sdo(axis, cs.encode_sdo_write(timeout_ep, "float", cfg.get("hw_watchdog_timeout_s")))
        self._sdo(axis, cs.encode_sdo_write(enable_ep, "bool", True))
        self._sdo(axis, cs.encode_sdo_read(timeout_ep))
        self._sdo(axis, cs.encode_sdo_read(enable_ep))

    def _sdo(self, axis: OdriveAxis, data: bytes) -> None:
        self._send(cs.make_frame(axis.spec.can_id, Cmd.RX_SDO, data))
