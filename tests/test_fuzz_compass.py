"""Seeded fuzz of the compass parsers through the real driver: NMEA sentences (HDG ... PTNTHPR)
and OS5000 ``$C`` lines, mutated from valid ones (checksums fixed most of the time so the fields
are reached). No exception may escape the driver's line handling, and nothing it publishes may be
non-finite or outside its range. Bounded (a few seconds); bench/fuzz.py runs the same longer."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from fuzz_targets import CompassTarget, FuzzViolation, check_compass_message, run_seeded

from u2sa_hw import lcmtypes as t


@pytest.mark.parametrize(("fmt", "count"), [("nmea", 50000), ("os5000", 50000)])
def test_mutated_compass_lines_never_escape_or_publish_impossible_values(tmp_path: Path, lcm_url: str, fmt: str,
                                                                        count: int) -> None:
    target = CompassTarget(fmt, workdir=tmp_path, lcm_url=lcm_url)
    try:
        run_seeded(target, seed=1311 if fmt == "nmea" else 5000, count=count)
        drv = target.driver
        # the mutations reached every outcome: published, dropped values, malformed, bad checksums
        assert drv.published > 100 and drv.malformed > 100 and sum(drv.bad_checksums.values()) > 100
        if fmt == "nmea":
            assert drv.out_of_range.total > 0 and drv.not_valid.total > 0
    finally:
        target.close()


@pytest.mark.parametrize("field, value", [("psi", math.nan), ("psi", math.pi), ("theta", 1.0e304), ("phi", -4.0),
                                          ("psi_dot", math.inf), ("psi_sigma", 0.0)])
def test_the_fuzz_check_catches_what_the_issue_saw_published(field: str, value: float) -> None:
    """The check the fuzz applies fails on the values once published (a NaN heading, a pitch of 1e304 rad)."""
    msg = t.StateInformation()
    msg.set(**{field: value})
    with pytest.raises(FuzzViolation):
        check_compass_message(msg)
