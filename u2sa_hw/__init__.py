"""u2sa-hw: the Universal Unmanned Systems Architecture as a runtime for Linux SBCs.

The package holds the service contract (``service``), the transport over LCM
(``transport``), the message types (``messages``), the vehicle profile (``vehicle``),
the port layer to hardware (``ports``), the core services (``services``) and the
``u2sa`` command line (``cli``).
"""

__version__ = "0.1.0"
