"""The local launcher (``u2sa run``): the services of a vehicle profile as supervised processes.

``Launcher`` is the library (``u2sa sim`` uses it), ``LauncherClient`` talks to a running
one over its control socket, ``RestartPolicy`` holds the backoff rules. See docs/supervision.md.
"""

from u2sa_hw.launcher.control import (SOCKET_ENV, LauncherBusy, LauncherClient, LauncherError,
                                      default_socket_path)
from u2sa_hw.launcher.children import select_services, u2sa_command
from u2sa_hw.launcher.launcher import Launcher
from u2sa_hw.launcher.output import PrefixedOutput
from u2sa_hw.launcher.policy import ProcessStatus, RestartPolicy
from u2sa_hw.launcher.process import SupervisedProcess

__all__ = [
    "Launcher", "LauncherBusy", "LauncherClient", "LauncherError", "PrefixedOutput", "ProcessStatus",
    "RestartPolicy", "SOCKET_ENV", "SupervisedProcess", "default_socket_path", "select_services", "u2sa_command",
]
