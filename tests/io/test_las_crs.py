"""The CRS of LAS / LAZ / COPC files from their VLRs (WKT record 2112, GeoTIFF keys 34735), with laspy only."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")
from laspy.vlrs.known import WktCoordinateSystemVlr  # noqa: E402
from builders import geokeys  # noqa: E402
from laspy.vlrs.vlrlist import VLRList  # noqa: E402

from hgca_core.io.las import las_header_info  # noqa: E402
from hgca_core.io.las_crs import files_crs, las_crs, wkt_epsg  # noqa: E402
from hgca_testdata import REAL_FIXTURES, require_real  # noqa: E402

UTM17_WKT = ('PROJCS["WGS 84 / UTM zone 17N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
             '298.257223563,AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0,'
             'AUTHORITY["EPSG","8901"]],UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],'
             'AUTHORITY["EPSG","4326"]],PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",-81],'
             'UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Easting",EAST],AXIS["Northing",NORTH],'
             'AUTHORITY["EPSG","32617"]]')
NO_CODE_WKT = ('PROJCS["local LCC",GEOGCS["NAD83",DATUM["NAD83",SPHEROID["GRS 1980",6378137,298.257222101]],'
               'UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]]],PROJECTION["Lambert_Conformal_Conic_2SP"],'
               'UNIT["foot",0.3048,AUTHORITY["EPSG","9002"]]]')
WKT2 = ('PROJCRS["ETRS89 / UTM zone 32N",BASEGEOGCRS["ETRS89",ID["EPSG",4258]],CONVERSION["UTM zone 32N",'
        'ID["EPSG",16032]],CS[Cartesian,2],LENGTHUNIT["metre",1,ID["EPSG",9001]],ID["EPSG",25832]]')


def write_las(path: Path, vlrs=(), evlrs=(), version: str = "1.2", wkt_bit: bool = False) -> Path:
    header = laspy.LasHeader(point_format=6 if version == "1.4" else 1, version=version)
    header.scales, header.offsets = [0.01] * 3, [500000.0, 4000000.0, 0.0]
    header.global_encoding.wkt = wkt_bit
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.array([500001.0, 500002.0]), np.array([4000001.0, 4000003.0]), np.array([1.0, 2.0])
    for vlr in vlrs:
        las.vlrs.append(vlr)
    if evlrs:
        las.evlrs = VLRList(list(evlrs))
    las.write(str(path))
    return path


def test_projected_geokey_gives_its_epsg(tmp_path: Path) -> None:
    path = write_las(tmp_path / "utm.las", [geokeys((1024, 1), (3072, 32617))])
    assert las_crs(str(path)) == "EPSG:32617"
    assert las_header_info(str(path))["crs"] == "EPSG:32617"


def test_geographic_key_when_no_projected_one(tmp_path: Path) -> None:
    path = write_las(tmp_path / "geo.las", [geokeys((1024, 2), (2048, 4326), (3072, 32767))])
    assert las_crs(str(path)) == "EPSG:4326"


def test_user_defined_keys_alone_give_no_crs(tmp_path: Path) -> None:
    path = write_las(tmp_path / "user.las", [geokeys((1024, 1), (2048, 32767), (3072, 32767))])
    assert las_crs(str(path)) is None


def test_wkt_root_authority_not_a_nested_one(tmp_path: Path) -> None:
    path = write_las(tmp_path / "wkt.laz", [WktCoordinateSystemVlr(UTM17_WKT)])
    assert las_crs(str(path)) == "EPSG:32617"
    assert wkt_epsg(NO_CODE_WKT) is None  # its units' EPSG:9122 and EPSG:9002 are not the CRS
    assert wkt_epsg(WKT2) == "EPSG:25832"
    assert wkt_epsg('PROJCS["a",AUTHORITY["EPSG","1"]') is None  # unbalanced


def test_wkt_without_a_code_is_kept_whole(tmp_path: Path) -> None:
    path = write_las(tmp_path / "lcc.las", [WktCoordinateSystemVlr(NO_CODE_WKT)])
    assert las_crs(str(path)) == NO_CODE_WKT


def test_the_wkt_bit_says_which_record_counts(tmp_path: Path) -> None:
    both = [geokeys((3072, 26917)), WktCoordinateSystemVlr(UTM17_WKT)]
    assert las_crs(str(write_las(tmp_path / "keys.las", both, version="1.4"))) == "EPSG:26917"
    assert las_crs(str(write_las(tmp_path / "wkt.las", both, version="1.4", wkt_bit=True))) == "EPSG:32617"


def test_las14_evlr_wkt(tmp_path: Path) -> None:
    path = write_las(tmp_path / "evlr.las", evlrs=[WktCoordinateSystemVlr(WKT2)], version="1.4", wkt_bit=True)
    with laspy.open(str(path)) as reader:  # the record really is an EVLR
        assert not reader.header.vlrs and reader.header.evlrs
    assert las_crs(str(path)) == "EPSG:25832"


def test_files_crs_agrees_or_says_nothing(tmp_path: Path) -> None:
    a = str(write_las(tmp_path / "a.las", [geokeys((3072, 32617))]))
    b = str(write_las(tmp_path / "b.las", [geokeys((3072, 32617))]))
    c = str(write_las(tmp_path / "c.las", [geokeys((3072, 32618))]))
    plain = str(write_las(tmp_path / "plain.las"))
    assert files_crs([a, b, plain]) == "EPSG:32617"
    assert files_crs([a, c]) is None
    assert files_crs([str(tmp_path / "x.ply")]) is None


def test_real_files_crs() -> None:
    """What the real aerial files carry: COPC a compound WKT (horizontal EPSG:2991), LAS 1.4 GeoTIFF EPSG:4326,
    Autzen a Lambert WKT without a code (its GeoTIFF keys are user-defined), plane.laz user-defined keys only."""
    assert las_crs(str(require_real(REAL_FIXTURES / "simple.copc.laz"))) == "EPSG:2991"
    assert las_crs(str(require_real(REAL_FIXTURES / "simple1_4.las"))) == "EPSG:4326"
    autzen = las_crs(str(require_real(REAL_FIXTURES / "autzen_trim.laz")))
    assert autzen.startswith('PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic"')
    assert las_crs(str(require_real(REAL_FIXTURES / "plane.laz"))) is None
    assert las_crs(str(require_real(REAL_FIXTURES / "simple.las"))) is None


def test_read_json_reports_the_crs(tmp_path: Path) -> None:
    path = write_las(tmp_path / "utm.las", [geokeys((3072, 32617))])
    done = subprocess.run([sys.executable, "-m", "hgca_core.cli", "read", str(path), "-o", str(tmp_path / "o.npz"),
                           "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["crs"] == "EPSG:32617"
