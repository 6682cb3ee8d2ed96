"""World Modeler service (requirement S3; thesis 3.2.3.3).

Loads the a-priori objects file (:mod:`.xml`), takes Object Descriptions and any extension
of them from exteroceptive sensors on ``OBJECTS``, places them in local NED with the latest
``STATE_ESTIMATE`` and associates them (:mod:`.model`), and publishes every object on
``WORLD`` (as its concrete type, in NED) followed by a ``WorldSummary`` of their UIDs on
``WORLD_SUMMARY`` at ``publish_rate_hz``. A body-frame (FRD) object that arrives without a
pose younger than ``max_pose_age_s`` cannot be placed: it is counted and logged once.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.world.model import PlacementError, Pose, WorldModel
from u2sa_hw.services.world.xml import XmlFileError, load_objects


class WorldModeler(U2SAService):
    """Keeps the objects around the vehicle and publishes them."""

    SERVICE_TYPE: ClassVar[str] = "world_modeler"
    CONFIG = (
        field("objects_file", "", "a-priori objects XML; a relative path is relative to the vehicle profile",
              file=True),
        field("expiry_s", 5.0, "an observed object not seen for this long is dropped (0: never)", ge=0, le=MAX_TIMEOUT_S),
        field("association_radius_m", 1.0, "objects without a UID from one source merge within this distance", ge=0, le=1000.0),
        field("publish_rate_hz", 2.0, "WORLD and WORLD_SUMMARY publications per second", gt=0, le=MAX_RATE_HZ),
        field("max_pose_age_s", 1.0, "a body-frame object needs a STATE_ESTIMATE at most this old", gt=0, le=MAX_TIMEOUT_S),
        field("default_radius_m", 0.0, "radius of an a-priori <Circle>/<Sphere> written without <radius> "
              "(the thesis's example has none), m; 0: a point", ge=0, le=10000.0),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._lock = threading.Lock()
        self.model = self._new_model()
        self.pose: Pose | None = None
        self.pose_time = 0.0
        self._unplaceable_logged: set[str] = set()
        self.register_subscriber(ch.OBJECTS, t.ObjectDescription, self._on_object)
        self.register_subscriber(ch.STATE_ESTIMATE, t.StateInformation, self._on_estimate)
        self.register_publisher(ch.WORLD, t.ObjectDescription)
        self.register_publisher(ch.WORLD_SUMMARY, t.WorldSummary)

    def _new_model(self) -> WorldModel:
        return WorldModel(origin=self.profile.origin, expiry_s=float(self.config.get("expiry_s")),
                          association_radius_m=float(self.config.get("association_radius_m")), logger=self.logger)

    def objects_path(self) -> Path | None:
        """The configured objects file, resolved against the profile's directory."""
        return self.profile.resolve_path(str(self.config.get("objects_file")))

    def load_a_priori(self) -> bool:
        """(Re)load the a-priori objects; on error keep what is there, log it and degrade."""
        path = self.objects_path()
        if path is None:
            return False
        try:
            objects = load_objects(path, origin=self.profile.origin,
                                   default_radius=float(self.config.get("default_radius_m")))
        except XmlFileError as exc:
            self.error(f"a-priori objects not loaded: {exc}")
            self.status = "degraded"
            return False
        now = time.monotonic()
        with self._lock:
            for uid in [u for u, tr in self.model.tracked.items() if tr.a_priori]:
                del self.model.tracked[uid]
            for obj in objects:
                self.model.add_a_priori(obj, now=now)
        self.status = "ok"
        self.logger.info("%d a-priori objects loaded from %s", len(objects), path)
        return True

    def check_config(self) -> None:
        """Refuse a negative default radius."""
        if float(self.config.get("default_radius_m")) < 0:
            raise ConfigError(f"{self.name}: default_radius_m must be >= 0 m (0: a point), "
                              f"got {self.config.get('default_radius_m')!r}")

    def setup(self) -> None:
        """Check the config and load the a-priori objects."""
        self.check_config()
        self.load_a_priori()

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply new settings live."""
        if name in ("objects_file", "default_radius_m"):
            self.load_a_priori()
        elif name == "expiry_s":
            self.model.expiry_s = float(value)
        elif name == "association_radius_m":
            self.model.association_radius_m = float(value)

    # -- inputs ------------------------------------------------------------------------------
    def _on_estimate(self, msg: t.StateInformation) -> None:
        pose = Pose.from_estimate(msg)
        if pose is not None:
            with self._lock:
                self.pose, self.pose_time = pose, time.monotonic()

    def _on_object(self, msg: Any) -> None:
        now = time.monotonic()
        with self._lock:
            fresh = self.pose is not None and now - self.pose_time <= float(self.config.get("max_pose_age_s"))
            try:
                self.model.observe(msg, now=now, pose=self.pose if fresh else None)
            except PlacementError as exc:
                key = str(exc).split(":")[0]
                if key not in self._unplaceable_logged:
                    self._unplaceable_logged.add(key)
                    self.logger.warning("%s (further ones only counted)", exc)

    # -- output --------------------------------------------------------------------------------
    def publish_world(self) -> None:
        """Expire old objects, publish each on WORLD and the summary on WORLD_SUMMARY."""
        with self._lock:
            self.model.expire(time.monotonic())
            objects = self.model.objects()
            uids = self.model.uids()
        for obj in objects:
            self.publish(ch.WORLD, obj)
        summary = t.WorldSummary()
        summary.uids, summary.num_objects = uids, len(uids)
        self.publish(ch.WORLD_SUMMARY, summary)

    def run(self) -> None:
        """Publish the world at ``publish_rate_hz``."""
        while self.wait(1.0 / max(0.1, float(self.config.get("publish_rate_hz")))):
            self.publish_world()

    def health_details(self) -> dict[str, Any]:
        """Object counts and association statistics."""
        with self._lock:
            s = self.model.stats
            a_priori = sum(1 for tr in self.model.tracked.values() if tr.a_priori)
            return {"objects": len(self.model.tracked), "a_priori": a_priori, "observations": s.observations,
                    "associated_by_uid": s.by_uid, "associated_by_proximity": s.by_proximity, "new": s.new,
                    "expired": s.expired, "unplaceable": s.unplaceable,
                    "pose_age_s": f"{time.monotonic() - self.pose_time:.2f}" if self.pose else "none"}
