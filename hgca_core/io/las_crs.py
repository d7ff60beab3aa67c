"""The coordinate reference system a LAS / LAZ / COPC file declares in its VLRs, as "EPSG:n" where it names one.

Two places can hold it (LAS 1.4 R15, section 2.5): an OGC WKT record (user "LASF_Projection", record 2112, in the
VLRs or, for LAS 1.4, the EVLRs) and the GeoTIFF key directory (record 34735). The header's WKT bit says which one
counts when both are there. Reading them needs only laspy: EPSG codes are taken from the GeoTIFF keys
(ProjectedCSTypeGeoKey 3072, else GeographicTypeGeoKey 2048) or from the WKT root's own AUTHORITY / ID (for a
compound system, its horizontal part's), never guessed from nested ones (a unit's EPSG:9002 is not the CRS).
A WKT without a code is returned whole; pyproj can read it, the add-on shows and keeps it as it is.

A malformed CRS record gives None: the points are still good, only their CRS is unknown.
"""
from __future__ import annotations

import re
from typing import Any

PROJECTION_USER = "LASF_Projection"
WKT_RECORD, GEOKEYS_RECORD = 2112, 34735
PROJECTED_KEY, GEOGRAPHIC_KEY = 3072, 2048
USER_DEFINED = 32767
_HORIZONTAL = ("PROJCS", "GEOGCS", "PROJCRS", "GEOGCRS", "GEODCRS", "GEOCCS", "BOUNDCRS")
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
