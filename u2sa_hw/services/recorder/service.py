"""Recorder service: records every channel (or those matching patterns) into MCAP.

Runs as a unit like the others (``u2sa service recorder``). Logs go to
``<data_dir>/recordings`` (or ``directory``), rotate by size and duration, carry the
vehicle profile and every service config as attachments, and are crash-safe to within
``flush_interval_s`` (at most 1 s). Below ``min_free_mb`` of free disk it stops
recording, stays up and says why in its health.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

from u2sa_hw.config.fields import field
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.recorder.capture import BusCapture
from u2sa_hw.profile.vehicle import VehicleProfile

# A file period, not a wait: one file a day is a sensible longest (0 still means never).
MAX_ROTATE_DURATION_S = 86400.0


def run_info(profile: VehicleProfile, url: str) -> RunInfo:
    """The profile, its service configs and identity, for a log's metadata and attachments."""
    attachments: dict[str, bytes] = {}
    if profile.path is not None and profile.path.exists():
        attachments["vehicle.toml"] = profile.path.read_bytes()
    from u2sa_hw.geofence_parse import profile_fence

    fence = profile_fence(profile)
    if fence is not None:   # resolved to local metres: u2sa log plot draws it without the .plan it may come from
        attachments["geofence.json"] = fence.to_json().encode()
    for name, spec in profile.services.items():
        if spec.config_path.exists():
            attachments[f"config/{name}.toml"] = spec.config_path.read_bytes()
    return RunInfo(vehicle=profile.name, system_id=profile.system_id, lcm_url=url, attachments=attachments)


class Recorder(U2SAService):
    """Records the bus into MCAP files."""

    SERVICE_TYPE: ClassVar[str] = "recorder"
    CONFIG = (
        field("directory", "", "where logs go (default: <data_dir>/recordings)"),
        field("prefix", "u2sa", "file name prefix; names are <prefix>-YYYYmmdd-HHMMSS.mcap"),
        field("include", ".*", "regex of channels to record"),
        field("exclude", "", "regex of channels not to record"),
        field("compression", "zstd", "zstd, lz4 or none"),
        field("rotate_size_mb", 512.0, "start a new file past this size (0: never)", ge=0, le=1000000.0),
        field("rotate_duration_s", 3600.0, "start a new file after this long (0: never)", ge=0, le=MAX_ROTATE_DURATION_S),
        field("flush_interval_s", 1.0, "close a chunk at least this often (at most 1 s)", gt=0, le=1.0),
        field("min_free_mb", 200.0, "stop recording below this much free disk", ge=0, le=1e9),
        field("queue_size", 20000, "messages buffered between the bus and the disk", ge=1, le=1000000),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        c = self.config
        directory = Path(c["directory"]) if c["directory"] else self.profile.data_dir / "recordings"
        self.writer = McapLogWriter(directory, prefix=c["prefix"], compression=c["compression"],
                                    rotate_size_mb=c["rotate_size_mb"], rotate_duration_s=c["rotate_duration_s"],
                                    run=run_info(self.profile, self.transport.url))
        self.capture = BusCapture(self.transport, self.writer, include=c["include"], exclude=c["exclude"],
                                  queue_size=c["queue_size"], flush_interval_s=c["flush_interval_s"],
                                  min_free_mb=c["min_free_mb"])

    def setup(self) -> None:
        """Start capturing."""
        self.capture.start()
        self.logger.info("recording to %s", self.writer.directory)

    def run(self) -> None:
        """Watch the capture; degrade (and stay up) when it stopped."""
        while self.wait(0.5):
            if self.capture.stats.stopped_reason and self.status != "degraded":
                self.status = "degraded"
                self.error(self.capture.stats.stopped_reason)

    def kill(self) -> None:
        """Finish the current file."""
        self.capture.stop()
        super().kill()

    def health_details(self) -> dict[str, Any]:
        """Files, counts, drops and queue depth."""
        s = self.capture.stats
        return {**self.writer.describe(), "written": s.written, "dropped": s.dropped, "filtered": s.filtered,
                "queue": self.capture.queue_depth, "stopped": s.stopped_reason}
