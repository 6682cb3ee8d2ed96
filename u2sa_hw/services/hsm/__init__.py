"""The Health and Status Monitor (HSM): heartbeats, data freshness, restarts, the failsafe.

``monitor`` holds the judgement (pure, clock passed in) and returns ``verdicts``; ``stamps``
reads when a heartbeat was sent from the service's own stamps; ``rules`` reads what to watch
from the vehicle profile; ``restarters`` restarts through systemd or the local launcher; and
``service`` is the U2SA service that ties them to the bus. See docs/supervision.md.
"""
