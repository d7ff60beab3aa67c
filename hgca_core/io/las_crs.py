"""The coordinate reference system a LAS / LAZ / COPC file declares in its VLRs, as "EPSG:n" where it names one.

Two places can hold it (LAS 1.4 R15, section 2.5): an OGC WKT record (user "LASF_Projection", record 2112, in the
VLRs or, for LAS 1.4, the EVLRs) and the GeoTIFF key directory (record 34735). The header's WKT bit says which one
counts when both are there. Reading them needs only laspy: EPSG codes are taken from the GeoTIFF keys
(ProjectedCSTypeGeoKey 3072, else GeographicTypeGeoKey 2048) or from the WKT root's own AUTHORITY / ID (for a
compound system, its horizontal part's), never guessed from nested ones (a unit's EPSG:9002 is not the CRS).
A WKT without a code is returned whole; pyproj can read it, the add-on shows and keeps it as it is.

A malformed CRS record gives None: the points are still good, only their CRS is unknown.

The CRS's unit matters too: hgca completes on 20 cm cells of metres, so a file in feet (State Plane, EPSG:2263)
or in degrees (EPSG:4326) is read as it is (`hgca read`, `hgca info`, the add-on keep the file's own numbers,
which its CRS describes) but refused for completion (`check_inputs`), as are files in different CRSs.
"""
from __future__ import annotations

import re
import os
from typing import Any, Sequence

from hgca_core.errors import InputError

PROJECTION_USER = "LASF_Projection"
WKT_RECORD, GEOKEYS_RECORD = 2112, 34735
PROJECTED_KEY, GEOGRAPHIC_KEY = 3072, 2048
USER_DEFINED = 32767
_HORIZONTAL = ("PROJCS", "GEOGCS", "PROJCRS", "GEOGCRS", "GEODCRS", "GEOCCS", "BOUNDCRS")
PROJECTED_UNITS_KEY, VERTICAL_UNITS_KEY, MODEL_TYPE_KEY, GEOGRAPHIC_MODEL = 3076, 4099, 1024, 2
METRE_CODE = 9001
# EPSG length units by code (GeoTIFF ProjLinearUnitsGeoKey / VerticalUnitsGeoKey): name, metres per unit
EPSG_UNITS = {9002: ("foot", 0.3048), 9003: ("US survey foot", 1200 / 3937), 9005: ("Clarke's foot", 0.3047972654),
              9014: ("fathom", 1.8288), 9030: ("nautical mile", 1852.0), 9036: ("kilometre", 1000.0),
              9093: ("statute mile", 1609.344), 9096: ("yard", 0.9144)}
# CRSs named by code alone, whose unit the code implies: the NAD83 State Plane zones in feet (EPSG:2222-2289,
# e.g. 2263 New York Long Island, US survey feet) and the common geographic systems (degrees).
FEET_CODES = range(2222, 2290)
GEOGRAPHIC_CODES = frozenset({4326, 4269, 4258, 4267, 4979, 4937, 4283, 7844})
_GEOGRAPHIC_ROOTS = ("GEOGCS", "GEOGCRS")
_TOKEN = re.compile(r'"(?:[^"]|"")*"|[\[\]()]|[^,\[\]()"]+|,')


def _records(header: Any) -> list[Any]:
    return [*header.vlrs, *(getattr(header, "evlrs", None) or [])]


def _wkt_text(record: Any) -> str | None:
    text = getattr(record, "string", None)
    if text is None:
        try:
            text = record.record_data_bytes().decode("utf-8", "replace")
        except Exception:  # noqa: BLE001 - a record laspy cannot give back has no usable WKT
            return None
    text = str(text).strip("\x00 \r\n\t")
    return text or None


def _geokey_epsg(record: Any) -> str | None:
    keys = {int(k.id): k for k in getattr(record, "geo_keys", [])}
    for key_id in (PROJECTED_KEY, GEOGRAPHIC_KEY):
        key = keys.get(key_id)
        if key is not None and int(key.tiff_tag_location) == 0 and 0 < int(key.value_offset) < USER_DEFINED:
            return f"EPSG:{int(key.value_offset)}"
    return None


def _parse(text: str) -> list | None:
    """The WKT as nested lists: [keyword, child, ...] with quoted strings unquoted; None when unbalanced."""
    stack: list[list] = [[]]
    pending: str | None = None
    for token in _TOKEN.findall(text):
        if token in "[(":
            node = [(pending or "").strip().upper()]
            stack[-1].append(node)
            stack.append(node)
            pending = None
        elif token in "])":
            if pending is not None and pending.strip():
                stack[-1].append(pending.strip())
            pending = None
            if len(stack) == 1:
                return None
            stack.pop()
        elif token == ",":
            if pending is not None and pending.strip():
                stack[-1].append(pending.strip())
            pending = None
        elif token.startswith('"'):
            stack[-1].append(token[1:-1].replace('""', '"'))
            pending = None
        else:
            pending = token
    if len(stack) != 1 or not stack[0] or not isinstance(stack[0][0], list):
        return None
    return stack[0][0]


def _own_code(node: list) -> str | None:
    """"EPSG:n" from a node's direct AUTHORITY["EPSG","n"] (WKT1) or ID["EPSG",n] (WKT2) child."""
    for child in node[1:]:
        if isinstance(child, list) and child[0] in ("AUTHORITY", "ID") and len(child) >= 3:
            if str(child[1]).upper() == "EPSG" and str(child[2]).strip().isdigit():
                return f"EPSG:{int(str(child[2]).strip())}"
    return None


def wkt_epsg(text: str) -> str | None:
    """The EPSG code of a WKT's root system, or of a compound system's horizontal part; None when it has none."""
    root = _parse(text)
    if root is None:
        return None
    code = _own_code(root)
    if code is None and root[0] in ("COMPD_CS", "COMPOUNDCRS"):
        horizontal = next((c for c in root[1:] if isinstance(c, list) and c[0] in _HORIZONTAL), None)
        code = _own_code(horizontal) if horizontal is not None else None
    return code


def header_crs(header: Any) -> str | None:
    """The CRS a laspy header declares: "EPSG:n", else the WKT itself, else None (none, or unreadable)."""
    records = [r for r in _records(header) if getattr(r, "user_id", "").rstrip("\x00") == PROJECTION_USER]
    wkts = [t for t in (_wkt_text(r) for r in records if int(r.record_id) == WKT_RECORD) if t]
    keys = [r for r in records if int(r.record_id) == GEOKEYS_RECORD]
    wkt_bit = bool(getattr(getattr(header, "global_encoding", None), "wkt", False))
    from_wkt = (wkt_epsg(wkts[0]) or wkts[0]) if wkts else None
    from_keys = next((c for c in map(_geokey_epsg, keys) if c), None)
    if wkt_bit:
        return from_wkt or from_keys
    return from_keys or from_wkt


def las_crs(path: str) -> str | None:
    """The CRS of one LAS / LAZ / COPC file from its header and (E)VLRs, without reading a point."""
    import laspy

    try:
        with laspy.open(path) as reader:
            return header_crs(reader.header)
    except Exception:  # noqa: BLE001 - the reader itself reports a broken file; here it only has no CRS
        return None


def files_crs(paths: list[str]) -> str | None:
    """The one CRS the LAS / LAZ / COPC files among `paths` declare; None when none does or they disagree."""
    found = {las_crs(p) for p in paths if str(p).lower().endswith((".las", ".laz"))}
    found.discard(None)
    return found.pop() if len(found) == 1 else None


def _unit_child(node: list) -> tuple[str, float] | None:
    """A node's own linear unit: a direct UNIT / LENGTHUNIT child (WKT1, WKT2 CS-wide), else its axes' (WKT2)."""
    for child in node[1:]:
        if isinstance(child, list) and child[0] in ("UNIT", "LENGTHUNIT") and len(child) >= 3:
            try:
                return str(child[1]), float(str(child[2]))
            except ValueError:
                return None
    for child in node[1:]:
        if isinstance(child, list) and child[0] == "AXIS":
            found = _unit_child(child)
            if found is not None:
                return found
    return None


def wkt_unit(text: str) -> tuple[str, float | None] | None:
    """(unit name, metres per unit; None for degrees) of a WKT's horizontal or vertical part that is not in
    metres; None when every part is in metres (or the WKT says nothing readable)."""
    root = _parse(text)
    if root is None:
        return None
    parts = [c for c in root[1:] if isinstance(c, list)] if root[0] in ("COMPD_CS", "COMPOUNDCRS") else [root]
    for part in parts:
        if part[0] == "BOUNDCRS":
            source = next((c for c in part[1:] if isinstance(c, list) and c[0] == "SOURCECRS"), None)
            part = next((c for c in (source or [])[1:] if isinstance(c, list)), part)
        if part[0] in _GEOGRAPHIC_ROOTS:
            return "degree", None
        unit = _unit_child(part) if part[0] not in ("AUTHORITY", "ID") else None
        if unit is not None and abs(unit[1] - 1.0) > 1e-9:
            return unit
    return None


def _code_unit(code: int) -> tuple[str, float | None]:
    name, factor = EPSG_UNITS.get(code, (f"EPSG unit {code}", None))
    return name, factor


def _geokey_unit(record: Any) -> tuple[str, float | None] | None:
    keys = {int(k.id): k for k in getattr(record, "geo_keys", [])}

    def value(key_id: int) -> int | None:
        key = keys.get(key_id)
        return int(key.value_offset) if key is not None and int(key.tiff_tag_location) == 0 else None

    projected = value(PROJECTED_KEY)
    if value(MODEL_TYPE_KEY) == GEOGRAPHIC_MODEL and not (projected and 0 < projected < USER_DEFINED):
        return "degree", None
    for key_id in (PROJECTED_UNITS_KEY, VERTICAL_UNITS_KEY):
        code = value(key_id)
        if code not in (None, 0, METRE_CODE, USER_DEFINED):
            return _code_unit(code)
    return None


def crs_unit(crs: str | None) -> tuple[str, float | None] | None:
    """The unit of a CRS as `header_crs` gives it ("EPSG:n" or a WKT) when it is not metres, else None."""
    if not crs:
        return None
    match = re.fullmatch(r"EPSG:(\d+)", crs.strip())
    if match is None:
        return wkt_unit(crs)
    code = int(match.group(1))
    if code in FEET_CODES:   # US survey or international feet, by zone: either is 0.3048 m to 2 ppm
        return "feet (a NAD83 State Plane zone in feet)", None
    if code in GEOGRAPHIC_CODES:
        return "degree", None
    return None


def header_unit(header: Any) -> tuple[str, float | None] | None:
    """The non-metre unit a laspy header's CRS records declare (WKT units, GeoTIFF unit keys, or the EPSG code's
    own), else None."""
    records = [r for r in _records(header) if getattr(r, "user_id", "").rstrip("\x00") == PROJECTION_USER]
    for r in records:
        if int(r.record_id) == WKT_RECORD:
            text = _wkt_text(r)
            unit = wkt_unit(text) if text else None
        elif int(r.record_id) == GEOKEYS_RECORD:
            unit = _geokey_unit(r)
        else:
            continue
        if unit is not None:
            return unit
    return crs_unit(header_crs(header))


def file_georef(path: str) -> tuple[str | None, tuple[str, float | None] | None]:
    """(CRS, non-metre unit or None) of one input: a LAS / LAZ / COPC file's records, an .npz's `crs` and
    `unit` (what `hgca read` wrote); (None, None) for anything else."""
    name = str(path).lower()
    if name.endswith((".las", ".laz")):
        import laspy

        try:
            with laspy.open(path) as reader:
                return header_crs(reader.header), header_unit(reader.header)
        except Exception:  # noqa: BLE001 - the reader itself reports a broken file
            return None, None
    if name.endswith(".npz"):
        return npz_georef(path)
    return None, None


def _text(z, key: str) -> str | None:
    """A 0-d string entry of an open .npz, or None."""
    if key not in z.files:
        return None
    value = z[key]
    return str(value[()]) if value.shape == () and value.dtype.kind == "U" and str(value[()]) else None


def npz_georef(path: str) -> tuple[str | None, tuple[str, float | None] | None]:
    """(`crs`, (`unit`, metres per unit) when `unit` is not metres) of an .npz `hgca read` wrote, else Nones."""
    import numpy as np

    try:
        with np.load(path, allow_pickle=False) as z:
            crs, unit = _text(z, "crs"), _text(z, "unit")
            factor = z["unit_metres"] if "unit_metres" in z.files else None
    except Exception:  # noqa: BLE001 - the reader itself reports a broken file
        return None, None
    if unit is None or unit == "metre":
        return crs, crs_unit(crs)
    known = {name: f for name, f in EPSG_UNITS.values()}
    f = float(factor) if factor is not None and np.asarray(factor).shape == () else known.get(unit)
    return crs, (unit, f)


def short_crs(crs: str) -> str:
    """A CRS for a message: the EPSG code, or a WKT's name (a WKT runs to hundreds of characters)."""
    if len(crs) <= 40:
        return crs
    name = crs.split('"')[1] if crs.count('"') >= 2 else crs[:40]
    return f'"{name}" (WKT)'


def check_inputs(paths: Sequence[str], metric: bool = True) -> tuple[str | None, tuple[str, float | None] | None]:
    """(the one CRS the inputs declare, their unit when not metres; None for what none declares), after refusing
    inputs in different CRSs or units (naming both files and both) and, with `metric`, inputs not in metres.

    Why refuse feet rather than convert: the completion would have to be converted back on every write (tile and
    merged meshes, every format, the add-on's import) to stay in the file's CRS; a mesh in metres labelled with a
    feet CRS lands 3.28 times too small in a GIS. A reprojection (PDAL, LAStools) keeps the CRS and its numbers in
    step, and the file is untouched until then. Degrees (a geographic CRS) cannot be put on metre cells at all."""
    first_crs: tuple[str, str] | None = None
    first_unit: tuple[str, tuple[str, float | None] | None] | None = None
    for path in map(os.fspath, paths):
        crs, unit = file_georef(path)
        if crs is not None:
            if first_crs is not None and crs != first_crs[1]:
                raise InputError(f"the scans are in different CRSs: {first_crs[0]} is in {short_crs(first_crs[1])}, "
                                 f"{path} in {short_crs(crs)}; reproject them to one CRS first", path)
            first_crs = first_crs or (path, crs)
        if metric and unit is not None:
            name, factor = unit
            what = f"{name} ({factor:g} m)" if factor else name
            raise InputError(f"its coordinates are in {what}" + (f", as its CRS {short_crs(crs)} says" if crs else "")
                             + ": hgca completes in metres (20 cm cells); reproject it to a CRS in metres (e.g. "
                             "UTM, with PDAL or LAStools) and complete that", path)
        if first_unit is not None and unit != first_unit[1] and (unit is not None or crs is not None):
            said = lambda u: u[0] if u else "metres"   # noqa: E731
            raise InputError(f"the scans are in different units: {first_unit[0]} in {said(first_unit[1])}, {path} "
                             f"in {said(unit)}", path)
        if first_unit is None and (unit is not None or crs is not None):
            first_unit = (path, unit)
    return (first_crs[1] if first_crs else None), (first_unit[1] if first_unit else None)
