"""Geodetic <-> ENU (pyproj pipeline) against a closed-form WGS84 implementation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from flowins.data import GnssStream
from flowins.geometry.geodesy import LocalTangentPlane, gnss_to_enu

# WGS84, written out here so that the truth does not come from PROJ.
A_M = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)

HELSINKI = (60.17, 24.94, 25.0)


def ecef_closed_form(lat_deg, lon_deg, h_m):
    """Geodetic -> ECEF: N(φ) = a / sqrt(1 - e² sin²φ)."""
    phi, lam = np.radians(lat_deg), np.radians(lon_deg)
    n = A_M / np.sqrt(1.0 - E2 * np.sin(phi) ** 2)
    return np.stack(
        [
            (n + h_m) * np.cos(phi) * np.cos(lam),
            (n + h_m) * np.cos(phi) * np.sin(lam),
            (n * (1.0 - E2) + h_m) * np.sin(phi),
        ],
        axis=-1,
    )


def enu_closed_form(lat_deg, lon_deg, h_m, origin):
    lat0, lon0, h0 = origin
    phi, lam = math.radians(lat0), math.radians(lon0)
    r = np.array(
        [
            [-math.sin(lam), math.cos(lam), 0.0],
            [-math.sin(phi) * math.cos(lam), -math.sin(phi) * math.sin(lam), math.cos(phi)],
            [math.cos(phi) * math.cos(lam), math.cos(phi) * math.sin(lam), math.sin(phi)],
        ]
    )
    d = ecef_closed_form(lat_deg, lon_deg, h_m) - ecef_closed_form(lat0, lon0, h0)
    return d @ r.T


def meridian_radius_m(lat_deg):
    """M(φ) = a (1 - e²) / (1 - e² sin²φ)^(3/2)."""
    s = math.sin(math.radians(lat_deg))
    return A_M * (1.0 - E2) / (1.0 - E2 * s * s) ** 1.5


def _points_around(origin, n=50, seed=0):
    rng = np.random.default_rng(seed)
    lat0, lon0, h0 = origin
    lat = lat0 + rng.uniform(-0.04, 0.04, n)  # about ±4.5 km north-south
    lon = lon0 + rng.uniform(-0.08, 0.08, n)  # about ±4.5 km east-west at 60° N
    h = h0 + rng.uniform(-50.0, 300.0, n)
    return lat, lon, h


@pytest.mark.parametrize("origin", [HELSINKI, (-33.45, -70.66, 570.0)])
def test_to_enu_matches_closed_form(origin):
    ltp = LocalTangentPlane(*origin)
    lat, lon, h = _points_around(origin)
    enu = ltp.to_enu(torch.tensor(lat, dtype=torch.float64), lon, h)
    assert enu.shape == (50, 3) and enu.dtype == torch.float64
    expected = enu_closed_form(lat, lon, h, origin)
    assert np.abs(expected[:, :2]).max() > 2000.0  # the points really are km away
    np.testing.assert_allclose(enu.numpy(), expected, rtol=0, atol=1e-6)


def test_origin_maps_to_zero():
    ltp = LocalTangentPlane(*HELSINKI)
    enu = ltp.to_enu(*HELSINKI)
    assert enu.shape == (3,)
    np.testing.assert_allclose(enu.numpy(), 0.0, atol=1e-9)


def test_point_1km_north_along_meridian():
    lat0, lon0, h0 = HELSINKI
    s_m = 1000.0
    # Arc length along the meridian: s = ∫ M dφ; M at the mid-latitude makes the
    # error third order (~1e-9 m here), so iterate on the midpoint twice.
    dphi_deg = math.degrees(s_m / meridian_radius_m(lat0))
    for _ in range(3):
        dphi_deg = math.degrees(s_m / meridian_radius_m(lat0 + dphi_deg / 2))
    enu = LocalTangentPlane(*HELSINKI).to_enu(lat0 + dphi_deg, lon0, h0).numpy()
    assert abs(enu[0]) < 1e-6
    # Locally the meridian is a circle of radius M; at height h0 above it the
    # point sits at angle Δφ = s/M on a circle of radius M + h0, so
    # N = (M + h0) sin Δφ ≈ s (1 + h0/M) - s³/(6M²)  (+3.9 mm, -4 µm here)
    # U = -(M + h0)(1 - cos Δφ) ≈ -s²/(2M)             (-7.8 cm).
    m = meridian_radius_m(lat0)
    assert enu[1] == pytest.approx(s_m * (1 + h0 / m) - s_m**3 / (6 * m**2), abs=1e-5)
    assert enu[2] == pytest.approx(-(s_m**2) / (2 * m), abs=1e-6)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_round_trip_and_batch_shapes(batch):
    ltp = LocalTangentPlane(*HELSINKI)
    rng = np.random.default_rng(1)
    lat = HELSINKI[0] + rng.uniform(-0.03, 0.03, batch)
    lon = HELSINKI[1] + rng.uniform(-0.06, 0.06, batch)
    h = HELSINKI[2] + rng.uniform(-20.0, 200.0, batch)
    enu = ltp.to_enu(lat, lon, h)
    assert enu.shape == (*batch, 3)
    lat2, lon2, h2 = ltp.to_geodetic(enu)
    assert lat2.shape == lon2.shape == h2.shape == batch
    np.testing.assert_allclose(lat2.numpy(), lat, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lon2.numpy(), lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(h2.numpy(), h, rtol=0, atol=1e-6)


def test_to_geodetic_inverts_closed_form_enu():
    ltp = LocalTangentPlane(*HELSINKI)
    lat, lon, h = _points_around(HELSINKI, n=10, seed=3)
    lat2, lon2, h2 = ltp.to_geodetic(torch.from_numpy(enu_closed_form(lat, lon, h, HELSINKI)))
    np.testing.assert_allclose(lat2.numpy(), lat, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lon2.numpy(), lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(h2.numpy(), h, rtol=0, atol=1e-6)


def test_gnss_to_enu_positions_covariances_and_origin():
    lat, lon, h = _points_around(HELSINKI, n=6, seed=2)
    h_acc = np.array([1.0, 2.0, 3.0, 0.5, 4.0, 2.5])
    v_acc = np.array([2.0, 3.0, 5.0, 1.0, 6.0, 3.5])
    gnss = GnssStream(np.arange(6.0), lat, lon, h, h_acc, v_acc)

    pos, cov, origin = gnss_to_enu(gnss.lat_deg, gnss.lon_deg, gnss.alt_m, gnss.h_acc_m, gnss.v_acc_m)
    torch.testing.assert_close(gnss.enu()[0], pos, rtol=0, atol=0)  # the stream's own view of the same
    assert origin == LocalTangentPlane(lat[0], lon[0], h[0])
    assert pos.shape == (6, 3) and cov.shape == (6, 3, 3)
    np.testing.assert_allclose(pos[0].numpy(), 0.0, atol=1e-9)
    np.testing.assert_allclose(pos.numpy(), enu_closed_form(lat, lon, h, (lat[0], lon[0], h[0])), atol=1e-6)
    for k in range(6):
        np.testing.assert_array_equal(cov[k].numpy(), np.diag([h_acc[k] ** 2, h_acc[k] ** 2, v_acc[k] ** 2]))

    ltp = LocalTangentPlane(*HELSINKI)
    pos2, _, origin2 = gnss.enu(ltp)
    assert origin2 is ltp
    np.testing.assert_allclose(pos2.numpy(), enu_closed_form(lat, lon, h, HELSINKI), atol=1e-6)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="origin_lat_deg"):
        LocalTangentPlane(91.0, 0.0, 0.0)
    ltp = LocalTangentPlane(*HELSINKI)
    with pytest.raises(ValueError, match=r"lat_deg is non-finite .* at index \(1,\)"):
        ltp.to_enu([60.0, float("nan")], 24.9, 0.0)
    with pytest.raises(ValueError, match=r"enu_m has shape \(4, 2\); expected \(\.\.\., 3\)"):
        ltp.to_geodetic(torch.zeros(4, 2, dtype=torch.float64))
