"""WGS84 geodetic coordinates <-> a local East-North-Up tangent plane, via pyproj.

The conversion is the PROJ pipeline

    geodetic (lon, lat, ellipsoidal h)  --+proj=cart-->  ECEF  --+proj=topocentric-->  ENU

i.e. ``enu = R(φ0, λ0) (ecef(φ, λ, h) - ecef(φ0, λ0, h0))`` with

    R = [[-sin λ0,          cos λ0,         0     ],
         [-sin φ0 cos λ0,  -sin φ0 sin λ0,  cos φ0],
         [ cos φ0 cos λ0,   cos φ0 sin λ0,  sin φ0]],

exact (no flat-earth approximation) at any distance from the origin. Heights are
ellipsoidal (WGS84), not above the geoid.

The functions run in numpy through PROJ: outputs are float64 CPU tensors and
carry no gradient to the inputs. They are preprocessing for measurements, not
part of the differentiable graph.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from pyproj import Transformer
from torch import Tensor

__all__ = ["LocalTangentPlane", "gnss_to_enu"]

_DTYPE = torch.float64


@functools.lru_cache(maxsize=64)
def _enu_transformer(lat0_deg: float, lon0_deg: float, alt0_m: float) -> Transformer:
    """The geodetic -> ENU pipeline for one origin (cached: building it costs ~ms)."""
    # repr() of a float is the shortest string that round-trips exactly.
    pipeline = (
        "+proj=pipeline "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0_deg!r} +lon_0={lon0_deg!r} +h_0={alt0_m!r}"
    )
    return Transformer.from_pipeline(pipeline)


def _as_numpy(value: Any) -> np.ndarray:
    if isinstance(value, Tensor):
        return value.detach().to(device="cpu", dtype=_DTYPE).numpy()
    return np.asarray(value, dtype=np.float64)


def _first_bad(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(mask)[0])


@dataclass(frozen=True)
class LocalTangentPlane:
    """A local East-North-Up frame whose origin is a WGS84 point.

    Attributes:
        origin_lat_deg: geodetic latitude of the origin, in [-90, 90] [deg].
        origin_lon_deg: longitude of the origin, in [-180, 180] [deg].
        origin_alt_m: ellipsoidal height of the origin [m].
    """

    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float

    def __post_init__(self) -> None:
        for key in ("origin_lat_deg", "origin_lon_deg", "origin_alt_m"):
            value = float(getattr(self, key))
            if not np.isfinite(value):
                raise ValueError(f"LocalTangentPlane: {key}={value!r}; expected a finite number")
            object.__setattr__(self, key, value)
        if not -90.0 <= self.origin_lat_deg <= 90.0:
            raise ValueError(f"LocalTangentPlane: origin_lat_deg={self.origin_lat_deg!r}; expected a value in [-90, 90]")
        if not -180.0 <= self.origin_lon_deg <= 180.0:
            raise ValueError(
                f"LocalTangentPlane: origin_lon_deg={self.origin_lon_deg!r}; expected a value in [-180, 180]"
            )

    @classmethod
    def at_first(cls, lat_deg: Tensor, lon_deg: Tensor, alt_m: Tensor) -> LocalTangentPlane:
        """The tangent plane at the first of the points ``(G,)`` (latitude, longitude, height)."""
        return cls(float(lat_deg[0]), float(lon_deg[0]), float(alt_m[0]))

    def _transformer(self) -> Transformer:
        return _enu_transformer(self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)

    def to_enu(self, lat_deg: Any, lon_deg: Any, alt_m: Any) -> Tensor:
        """Geodetic -> ENU.

        Args:
            lat_deg, lon_deg, alt_m: broadcastable arrays, tensors or floats of
                latitude [deg], longitude [deg] and ellipsoidal height [m].

        Returns:
            ``(..., 3)`` float64 ``(east, north, up)`` [m], ``...`` the broadcast shape.
        """
        lat, lon, alt = np.broadcast_arrays(_as_numpy(lat_deg), _as_numpy(lon_deg), _as_numpy(alt_m))
        for key, x in (("lat_deg", lat), ("lon_deg", lon), ("alt_m", alt)):
            if not np.isfinite(x).all():
                idx = _first_bad(~np.isfinite(x))
                raise ValueError(f"to_enu: {key} is non-finite ({x[idx]}) at index {idx}; expected finite numbers")
        if ((lat < -90.0) | (lat > 90.0)).any():
            idx = _first_bad((lat < -90.0) | (lat > 90.0))
            raise ValueError(f"to_enu: lat_deg={lat[idx]!r} at index {idx}; expected a value in [-90, 90]")
        e, n, u = self._transformer().transform(lon.ravel(), lat.ravel(), alt.ravel())
        enu = np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=-1).reshape(*lat.shape, 3)
        if not np.isfinite(enu).all():
            idx = _first_bad(~np.isfinite(enu).all(axis=-1))
            raise ValueError(f"to_enu: PROJ returned a non-finite ENU position at index {idx}")
        return torch.from_numpy(np.array(enu, dtype=np.float64))

    def to_geodetic(self, enu_m: Any) -> tuple[Tensor, Tensor, Tensor]:
        """ENU -> geodetic, the inverse of :meth:`to_enu`.

        Args:
            enu_m: ``(..., 3)`` ``(east, north, up)`` [m].

        Returns:
            ``(lat_deg, lon_deg, alt_m)``, each ``(...)`` float64; longitude in [-180, 180].
        """
        enu = _as_numpy(enu_m)
        if enu.ndim == 0 or enu.shape[-1] != 3:
            raise ValueError(f"to_geodetic: enu_m has shape {enu.shape}; expected (..., 3)")
        if not np.isfinite(enu).all():
            idx = _first_bad(~np.isfinite(enu))
            raise ValueError(f"to_geodetic: enu_m is non-finite ({enu[idx]}) at index {idx}; expected finite numbers")
        batch = enu.shape[:-1]
        flat = enu.reshape(-1, 3)
        lon, lat, alt = self._transformer().transform(flat[:, 0], flat[:, 1], flat[:, 2], direction="INVERSE")
        out = []
        for x in (lat, lon, alt):
            out.append(torch.from_numpy(np.array(x, dtype=np.float64).reshape(batch)))
        if not all(bool(torch.isfinite(x).all()) for x in out):
            raise ValueError("to_geodetic: PROJ returned a non-finite geodetic position")
        return out[0], out[1], out[2]


def gnss_to_enu(
    lat_deg: Tensor, lon_deg: Tensor, alt_m: Tensor, h_acc_m: Tensor, v_acc_m: Tensor, *,
    origin: LocalTangentPlane | None = None,
) -> tuple[Tensor, Tensor, LocalTangentPlane]:
    """GNSS fixes as ENU positions with their measurement noise.

    Args:
        lat_deg, lon_deg, alt_m: ``(G,)`` the fixes (degrees, metres).
        h_acc_m, v_acc_m: ``(G,)`` their horizontal (per axis) and vertical 1-σ (m).
        origin: tangent plane to express them in; the first fix when ``None``.

    Returns:
        ``pos_enu_m`` ``(G, 3)`` [m]; ``cov_m2`` ``(G, 3, 3)`` =
        ``diag(h_acc_m², h_acc_m², v_acc_m²)`` [m²]; and the origin used.
    """
    if origin is None:
        origin = LocalTangentPlane.at_first(lat_deg, lon_deg, alt_m)
    pos = origin.to_enu(lat_deg, lon_deg, alt_m)
    var = torch.stack((h_acc_m, h_acc_m, v_acc_m), dim=-1).to(_DTYPE) ** 2
    return pos, torch.diag_embed(var), origin
