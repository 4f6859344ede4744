"""The geo-reference read from IFC files (graph.geo), against values typed by hand from the IFC text."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.graph.geo import dms_to_deg, geo_reference_of, read_geo_reference


def _metres_per_deg_lat(lat_deg: float, h_m: float) -> float:
    """m per degree of latitude at height h_m above the WGS84 ellipsoid (meridian radius of curvature + h)."""
    a, e2 = 6378137.0, 6.69437999014e-3
    s2 = np.sin(np.radians(lat_deg)) ** 2
    return (a * (1 - e2) / (1 - e2 * s2) ** 1.5 + h_m) * np.pi / 180


def test_fzk_haus(fzk_path) -> None:
    """fzk_haus.ifc: #389 IFCSITE(..., (49,6,1,566000), (8,26,11,540400), 110., ...) at placement #115 (origin);
    #62 IFCGEOMETRICREPRESENTATIONCONTEXT($,'Model',3,1.E-5,#59,#60) with #60 IFCDIRECTION((0.766044443119,
    0.642787609687)): true north 40 deg from +x, i.e. 50 deg clockwise from +y."""
    geo = read_geo_reference(fzk_path)
    assert geo is not None and geo.source == "IfcSite" and geo.crs is None and geo.north_given
    assert geo.latitude_deg == pytest.approx(49 + 6 / 60 + 1.566 / 3600, abs=1e-12)  # 49.1004350
    assert geo.longitude_deg == pytest.approx(8 + 26 / 60 + 11.5404 / 3600, abs=1e-12)  # 8.4365390
    assert geo.altitude_m == 110.0
    assert np.allclose(geo.north_cad, [0.766044443119, 0.642787609687], atol=1e-9)
    assert geo.true_north_deg == pytest.approx(-50.0, abs=1e-6)
    # 10 m along true north from the origin: latitude + 10 m / (m per degree), longitude unchanged
    p_cad = 10.0 * np.r_[geo.north_cad, 0.0]
    lat, lon, alt = geo.wgs84(p_cad)[0]
    assert lat - geo.latitude_deg == pytest.approx(10.0 / _metres_per_deg_lat(geo.latitude_deg, 110.0),
                                                    abs=1e-11)
    assert lon == pytest.approx(geo.longitude_deg, abs=1e-10) and alt == pytest.approx(110.0, abs=1e-4)
    # ENU: true north is +y, east is +x
    T = geo.T_enu_cad()
    assert np.allclose(T[:3, :3] @ np.r_[geo.north_cad, 0.0], [0, 1, 0])
    assert np.allclose(T[:3, :3] @ np.r_[geo.north_cad[1], -geo.north_cad[0], 0.0], [1, 0, 0])


def test_office_a(office_path) -> None:
    """office_a.ifc: #11652 IFCSITE(..., (42,21,30,344238), (-71,-3,-35,-194702), -0.0, ...); context #4 has no
    TrueNorth ($): +y by the schema's default, reported as not given."""
    geo = read_geo_reference(office_path)
    assert geo is not None and geo.source == "IfcSite"
    assert geo.latitude_deg == pytest.approx(42 + 21 / 60 + 30.344238 / 3600, abs=1e-12)  # 42.3584290
    assert geo.longitude_deg == pytest.approx(-(71 + 3 / 60 + 35.194702 / 3600), abs=1e-12)  # -71.0597763
    assert geo.altitude_m == 0.0 and not geo.north_given and geo.true_north_deg == 0.0
    assert np.allclose(geo.T_enu_cad(), np.eye(4))


def test_dms_and_none() -> None:
    assert dms_to_deg((49, 6, 1, 566000)) == pytest.approx(49.100435)
    assert dms_to_deg(None) is None


def test_map_conversion_ifc4() -> None:
    """IFC4 IfcMapConversion to EPSG:25832 (UTM 32N): the origin's eastings/northings give its latitude/longitude,
    a CAD step along x moves (a, b) in the grid; height is OrthogonalHeight + z."""
    import ifcopenshell
    from pyproj import Transformer

    f = ifcopenshell.file(schema="IFC4")
    origin = f.createIfcAxis2Placement3D(f.createIfcCartesianPoint((0.0, 0.0, 0.0)))
    ctx = f.createIfcGeometricRepresentationContext(None, "Model", 3, 1e-5, origin, None)
    crs = f.createIfcProjectedCRS(Name="EPSG:25832")
    f.createIfcMapConversion(ctx, crs, 458000.0, 5438000.0, 110.0, np.cos(0.3), np.sin(0.3), 1.0)
    geo = geo_reference_of(f)
    assert geo is not None and geo.source == "IfcMapConversion" and geo.crs == "EPSG:25832"
    to_lonlat = Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True).transform
    lon0, lat0 = to_lonlat(458000.0, 5438000.0)
    lon1, lat1 = to_lonlat(458000.0 + 10 * np.cos(0.3), 5438000.0 + 10 * np.sin(0.3))
    got = geo.wgs84(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 2.0]]))
    assert np.allclose(got[0], [lat0, lon0, 110.0], atol=1e-10)
    assert np.allclose(got[1], [lat1, lon1, 112.0], atol=1e-10)
    assert geo.true_north_deg == pytest.approx(-np.degrees(0.3))  # grid north, 0.3 rad clockwise from +y


def test_no_geo_reference(tmp_path) -> None:
    import ifcopenshell

    f = ifcopenshell.file(schema="IFC2X3")
    f.createIfcSite(ifcopenshell.guid.new())
    assert geo_reference_of(f) is None
    assert read_geo_reference(tmp_path / "building.obj") is None
