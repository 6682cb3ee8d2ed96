"""Geodetic <-> local NED about the vehicle profile's origin, and angle helpers.

The local frame is NED (x north, y east, z down, metres) about ``[vehicle] origin`` of the
profile (:class:`u2sa_hw.profile.vehicle.Origin`: lat, lon in degrees, alt in metres up).

The projection is a local flat-earth (equirectangular) one: a latitude difference is
scaled by the WGS84 meridian radius of curvature and a longitude difference by the
prime-vertical radius times cos(origin latitude), both taken at the origin's latitude
(and raised by its altitude). Within a few kilometres of the origin the error is a few
centimetres per kilometre squared, far below GPS noise; beyond ~10 km use a proper
projection. The two functions are exact inverses of each other. Altitude is metres up,
so ``down = origin.alt - alt``. Longitude differences wrap, so an origin near the
antimeridian works. ``mock_devices/vehicle_sim.py`` uses the same projection, so the
simulated GPS and the estimator agree to the millimetre.
"""

from __future__ import annotations

import math
from typing import Protocol

WGS84_A = 6378137.0            # semi-major axis, m
WGS84_E2 = 6.69437999014e-3    # first eccentricity squared


class GeoOrigin(Protocol):
    """Anything with ``lat``, ``lon`` (degrees) and ``alt`` (m up), e.g. ``VehicleProfile.origin``."""

    lat: float
    lon: float
    alt: float


def radii_of_curvature(lat_deg: float) -> tuple[float, float]:
    """WGS84 meridian (north) and prime-vertical (east) radii of curvature in m at *lat_deg*."""
    s = math.sin(math.radians(lat_deg))
    w = math.sqrt(1.0 - WGS84_E2 * s * s)
    return WGS84_A * (1.0 - WGS84_E2) / w**3, WGS84_A / w


def geodetic_to_ned(lat: float, lon: float, alt: float | None = None, *,
                    origin: GeoOrigin) -> tuple[float, float, float]:
    """(north, east, down) in m of a geodetic point (deg, deg, m up) about *origin*.

    With *alt* None the point is taken at the origin's altitude (down = 0).
    """
    r_north, r_east = radii_of_curvature(origin.lat)
    north = math.radians(lat - origin.lat) * (r_north + origin.alt)
    dlon = (lon - origin.lon + 180.0) % 360.0 - 180.0
    east = math.radians(dlon) * (r_east + origin.alt) * math.cos(math.radians(origin.lat))
    down = 0.0 if alt is None else origin.alt - alt
    return north, east, down


def ned_to_geodetic(north: float, east: float, down: float = 0.0, *,
                    origin: GeoOrigin) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m up) of a NED point in m about *origin*; inverse of :func:`geodetic_to_ned`."""
    r_north, r_east = radii_of_curvature(origin.lat)
    lat = origin.lat + math.degrees(north / (r_north + origin.alt))
    lon = origin.lon + math.degrees(east / ((r_east + origin.alt) * math.cos(math.radians(origin.lat))))
    lon = (lon + 180.0) % 360.0 - 180.0
    return lat, lon, origin.alt - down


def wrap_angle(angle: float) -> float:
    """*angle* in radians wrapped into [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def body_to_ned(forward: float, right: float, psi: float) -> tuple[float, float]:
    """Rotate a horizontal body (FRD) vector into (north, east) for heading *psi* (rad, clockwise from north)."""
    c, s = math.cos(psi), math.sin(psi)
    return forward * c - right * s, forward * s + right * c


def ned_to_body(north: float, east: float, psi: float) -> tuple[float, float]:
    """Rotate a horizontal (north, east) vector into body (forward, right) for heading *psi*."""
    c, s = math.cos(psi), math.sin(psi)
    return north * c + east * s, -north * s + east * c
