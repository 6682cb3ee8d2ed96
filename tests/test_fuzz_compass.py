"""Seeded fuzz of the compass parsers through the real driver: NMEA sentences (HDG ... PTNTHPR)
and OS5000 ``$C`` lines, mutated from valid ones (checksums fixed most of the time so the fields
are reached). No exception may escape the driver's line handling, and nothing it publishes may be
non-finite or outside its range. Bounded (a few seconds); bench/fuzz.py runs the same longer."""

from __future__ import annotations

from pathlib import Path

import pytest
from fuzz_targets import CompassTarget, run_seeded


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
