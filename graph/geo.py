"""The geo-reference of a building model: where its CAD frame lies on the Earth, read from the IFC, never guessed.

Two sources, the first found wins:
- IFC4 `IfcMapConversion` (with its `IfcProjectedCRS`): CAD (x, y, z) maps to the CRS's grid as
  E = Eastings + s (a x - b y), N = Northings + s (b x + a y), H = OrthogonalHeight + z, with (a, b) the unit
  (XAxisAbscissa, XAxisOrdinate) and s its Scale; latitude/longitude through pyproj from the named CRS. The ENU
  frame's axes are the grid's (meridian convergence, under a degree or two near a zone's centre, is not applied).
- `IfcSite` RefLatitude/RefLongitude/RefElevation (IFC2X3 and IFC4) at the site's placement, with the model
  context's `TrueNorth` (the direction of true north in the CAD x/y plane; +y where the file gives none, as the
  IFC schema defines). Latitude/longitude of other points through a topocentric (ENU) frame at that origin on
  the WGS84 ellipsoid (pyproj), with RefElevation taken as the origin's height.
A model with neither has no geo-reference: `read_geo_reference` returns None.

Frames: `cad` (the model's, metres, z up), `enu` (x east, y north, z up, metres, origin at the geo-reference's
origin). `T_enu_cad` maps CAD points into it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


def dms_to_deg(compound: tuple | list | None) -> float | None:
    """IfcCompoundPlaneAngleMeasure (degrees, minutes, seconds[, millionths of a second]; each signed) -> degrees."""
    if not compound:
        return None
    parts = [float(v) for v in compound] + [0.0] * (4 - len(compound))
    return parts[0] + parts[1] / 60.0 + (parts[2] + parts[3] * 1e-6) / 3600.0


@dataclass(frozen=True)
class GeoReference:
    """Where the CAD frame lies: `origin_cad` (3,) is at latitude/longitude (deg, WGS84) and altitude_m; true north
    points along `north_cad` (unit (2,), CAD x/y). `crs`: the projected CRS's name where the IFC names one."""

    source: str  # "IfcMapConversion" | "IfcSite"
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    origin_cad: np.ndarray
    north_cad: np.ndarray
    crs: str | None = None
    north_given: bool = True  # False where the file gives no TrueNorth and +y is the schema's default
    map_conversion: dict[str, float] | None = None  # eastings, northings, orthogonal_height, a, b, scale

    @property
    def true_north_deg(self) -> float:
        """Angle from the CAD frame's +y axis to true north, counter-clockwise positive, degrees."""
        return float(np.degrees(np.arctan2(-self.north_cad[0], self.north_cad[1])))

    def T_enu_cad(self) -> np.ndarray:
        """4x4: CAD points (metres) into ENU at the origin: east = north x up in the CAD plane."""
        nx, ny = self.north_cad
        R = np.array([[ny, -nx, 0.0], [nx, ny, 0.0], [0.0, 0.0, 1.0]])  # rows: east, north, up in CAD
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = -R @ self.origin_cad
        return T

    def wgs84(self, points_cad: np.ndarray) -> np.ndarray:
        """(N, 3) latitude (deg), longitude (deg), altitude (m) of CAD points (N, 3)."""
        p = np.asarray(points_cad, float).reshape(-1, 3)
        if self.map_conversion is not None:
            m = self.map_conversion
            e = m["eastings"] + m["scale"] * (m["a"] * p[:, 0] - m["b"] * p[:, 1])
            n = m["northings"] + m["scale"] * (m["b"] * p[:, 0] + m["a"] * p[:, 1])
            lon, lat = _grid_to_lonlat(self.crs or "")(e, n)
            return np.column_stack([lat, lon, m["orthogonal_height"] + p[:, 2]])
        enu = p @ self.T_enu_cad()[:3, :3].T + self.T_enu_cad()[:3, 3]
        lon, lat, h = _topocentric_to_lonlath(self.latitude_deg, self.longitude_deg, self.altitude_m)(
            enu[:, 0], enu[:, 1], enu[:, 2])
        return np.column_stack([lat, lon, h])

    def to_json(self) -> dict:
        doc = {"source": self.source, "latitude_deg": round(self.latitude_deg, 9),
               "longitude_deg": round(self.longitude_deg, 9), "altitude_m": round(self.altitude_m, 4),
               "origin_cad": [round(float(v), 6) for v in self.origin_cad],
               "true_north_deg": round(self.true_north_deg, 6),
               "north_cad": [round(float(v), 9) for v in self.north_cad], "north_given": self.north_given,
               "crs": self.crs}
        if self.map_conversion is not None:
            doc["map_conversion"] = {k: round(v, 6) for k, v in self.map_conversion.items()}
        return doc


@cache
def _grid_to_lonlat(crs: str):  # noqa: ANN202 - a pyproj transform function
    from pyproj import Transformer

    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform


@cache
def _topocentric_to_lonlath(lat_deg: float, lon_deg: float, h_m: float):  # noqa: ANN202
    from pyproj import Transformer

    pipeline = (f"+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={lat_deg!r} +lon_0={lon_deg!r} "
                f"+h_0={h_m!r} +step +inv +proj=cart +ellps=WGS84")
    return Transformer.from_pipeline(pipeline).transform


def read_geo_reference(path: Path) -> GeoReference | None:
    """The geo-reference of an IFC file (module doc), or None where it has none (or it is not an IFC file)."""
    if Path(path).suffix.lower() != ".ifc":
        return None
    from macroloc.graph.bim_ifc import open_ifc

    return geo_reference_of(open_ifc(Path(path)))


def geo_reference_of(ifc: Any) -> GeoReference | None:
    import ifcopenshell.util.placement
    import ifcopenshell.util.unit

    unit_m = float(ifcopenshell.util.unit.calculate_unit_scale(ifc))
    north = _true_north(ifc)
    if ifc.schema != "IFC2X3":
        for conv in ifc.by_type("IfcMapConversion"):
            return _from_map_conversion(conv, unit_m)
    for site in ifc.by_type("IfcSite"):
        lat, lon = dms_to_deg(site.RefLatitude), dms_to_deg(site.RefLongitude)
        if lat is None or lon is None:
            continue
        origin = np.zeros(3)
        if site.ObjectPlacement is not None:
            origin = ifcopenshell.util.placement.get_local_placement(site.ObjectPlacement)[:3, 3] * unit_m
        return GeoReference("IfcSite", lat, lon, float(site.RefElevation or 0.0) * unit_m, origin,
                            north if north is not None else np.array([0.0, 1.0]), north_given=north is not None)
    return None


def _true_north(ifc: Any) -> np.ndarray | None:
    """The 3D model context's TrueNorth (x, y) as a unit vector; None where the file gives none."""
    for ctx in ifc.by_type("IfcGeometricRepresentationContext"):
        if ctx.is_a("IfcGeometricRepresentationSubContext") or ctx.TrueNorth is None:
            continue
        if ctx.ContextType not in (None, "Model"):
            continue
        v = np.array(ctx.TrueNorth.DirectionRatios[:2], float)
        if np.linalg.norm(v) > 0:
            return v / np.linalg.norm(v)
    return None


def _from_map_conversion(conv: Any, unit_m: float) -> GeoReference:
    a, b = float(conv.XAxisAbscissa or 1.0), float(conv.XAxisOrdinate or 0.0)
    norm = float(np.hypot(a, b))
    a, b = a / norm, b / norm
    crs = conv.TargetCRS.Name if conv.TargetCRS is not None else None
    m = {"eastings": float(conv.Eastings), "northings": float(conv.Northings),
         "orthogonal_height": float(conv.OrthogonalHeight), "a": a, "b": b,
         "scale": float(conv.Scale) if conv.Scale is not None else unit_m}
    # grid north (+N) in CAD x/y: the inverse of the rotation by (a, b) applied to (0, 1)
    north_cad = np.array([b, a])
    lon, lat = _grid_to_lonlat(crs)(m["eastings"], m["northings"]) if crs else (float("nan"), float("nan"))
    return GeoReference("IfcMapConversion", float(lat), float(lon), m["orthogonal_height"], np.zeros(3), north_cad,
                        crs=crs, map_conversion=m)
