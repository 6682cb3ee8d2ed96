"""``u2sa check``: everything a vehicle profile says, checked before anything runs.

:func:`check_profile` (offline: the profile against what the code declares) returns every
:class:`Problem` at once; :mod:`u2sa_hw.check.probe` opens each device and looks at it.
``u2sa run``, ``u2sa sim`` and ``u2sa install`` call :func:`check_profile` first and refuse
to go on with errors. See docs/check.md.
"""

from u2sa_hw.check.offline import check_profile
from u2sa_hw.check.problem import ERROR, WARNING, Problem, errors_of

__all__ = ["ERROR", "WARNING", "Problem", "check_profile", "errors_of"]
