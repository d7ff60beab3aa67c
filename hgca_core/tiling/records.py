"""What a resumed drive checks before it reuses anything in its folder: drive.json, each cached tile, each tile mesh.

A drive folder outlives the run that wrote it: files get cut short (a full disk, a copy), copied in from another
drive, or edited by hand. So each finished tile carries what it was made from (`made_from`: its region, scans
by content, seed, settings, weights by digest, the neighbours it is conditioned on), inside its cache entry and in
its drive.json record, with the sha256 of every file it wrote (`checksums`). On reuse, drive.json is checked for
the types the drive wrote (`check_record`), every cache entry against its tile and its record
(`DriveStore.check_entry`), and every tile mesh against its checksum (`check_meshes`); what fails is made again
from what can be trusted, with one warning line saying which tile and why. Files a drive owns that are not this
plan's finished tiles (an earlier run with another --size, say) are removed (`sweep`), so no stale mesh stays
under a name the drive writes.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from typing import Any, Callable

from hgca_core.config import MESH_FORMATS
from hgca_core.errors import HgcaWarning
from hgca_core.tiling.tile import KEY_VERSION, TileJob

MESH_NAME = re.compile(rf"^\d+_s\d+\.({'|'.join(MESH_FORMATS)})$")       # DIR/tiles/<i>_s<k>.<ext>
DRIVE_NAME = re.compile(rf"^drive_s\d+\.({'|'.join(MESH_FORMATS)})$")    # DIR/drive_s<k>.<ext>


def made_from(job: TileJob) -> dict:
    """What a tile's result is a function of, as JSON (everything its key hashes, spelt out)."""
    return json.loads(json.dumps({
        "key_version": KEY_VERSION, "region": [float(v) for v in job.region], "scans": list(job.scans),
        "scans_sha256": list(job.scan_digests), "seed": job.seed, "settings": job.settings.keyed(),
        "weights_sha256": list(job.weights), "conditioned_on": list(job.conditioned_on)}))


def sha256_file(path: str | os.PathLike) -> str:
    """sha256 of a file as it is now (never cached: a file copied over another may keep its size and mtime)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# -- drive.json: the types the drive writes ------------------------------------------------------------------------

class _Opt:
    """A field that may be missing."""

    def __init__(self, spec: Any) -> None:
        self.spec = spec


class _Map:
    """An object with any keys, each value of `spec`."""

    def __init__(self, spec: Any) -> None:
        self.spec = spec


INT, NUM, STR, BOOL, NONE = "int", "num", "str", "bool", type(None)
_TILE = {"index": INT, "key": STR, "status": STR, "outputs": [STR],
         **{k: _Opt(v) for k, v in {
             "phase": INT, "arc": NUM, "region": [NUM], "scans": [INT], "seeds": [INT], "conditioned_on": [INT],
             "seconds": (NUM, NONE), "worker": (STR, NONE), "run": (INT, NONE), "peak_rss": (INT, NONE),
             "faces": ([INT], NONE), "started": (NUM, NONE), "finished": (NUM, NONE),
             "fixed_cells": ([INT], NONE), "free_cells": ([(INT, NONE)], NONE), "made_from": _Map(object),
             "sha256": _Map(STR)}.items()}}
_PLAN = {k: _Opt(v) for k, v in {"size": [NUM], "overlap": NUM, "stride": NUM, "scans_per_tile": INT,
                                  "length": NUM, "seams": BOOL, "mesh_format": STR}.items()}
RECORD = {"format": INT, "runs": INT, "tiles": [_TILE],
          **{k: _Opt(v) for k, v in {
              "status": STR, "pid": (INT, NONE), "host": STR, "engine": STR, "workers": INT, "threads": INT,
              "address": (STR, NONE), "tile_memory": (NUM, NONE), "settings": _Map(object), "plan": _PLAN,
              "scans": [_Map(object)], "outputs": [STR], "timings": _Map((NUM, NONE)), "error": STR}.items()}}


def check_record(doc: Any) -> str:
    """'' when drive.json's content has every field a resume reads, each of the type the drive writes; else the
    first problem, naming the key (`tiles[2].key is a list, not a string`)."""
    return _check(doc, RECORD, "") or ("" if doc["runs"] >= 0 else "runs is negative")


def _check(value: Any, spec: Any, where: str) -> str:
    if isinstance(spec, tuple):
        problems = [_check(value, s, where) for s in spec]
        return "" if "" in problems else problems[0]
    if spec is NONE:
        return "" if value is None else f"{where} is {_kind(value)}, not null"
    if spec is object:
        return ""
    if isinstance(spec, str):
        ok = {INT: isinstance(value, int) and not isinstance(value, bool),
              NUM: isinstance(value, (int, float)) and not isinstance(value, bool),
              STR: isinstance(value, str), BOOL: isinstance(value, bool)}[spec]
        names = {INT: "a whole number", NUM: "a number", STR: "a string", BOOL: "true or false"}
        return "" if ok else f"{where or 'drive.json'} is {_kind(value)}, not {names[spec]}"
    if isinstance(spec, list):
        if not isinstance(value, list):
            return f"{where} is {_kind(value)}, not a list"
        return next((p for i, v in enumerate(value) if (p := _check(v, spec[0], f"{where}[{i}]"))), "")
    if not isinstance(value, dict):
        return f"{where or 'drive.json'} is {_kind(value)}, not an object"
    if isinstance(spec, _Map):
        return next((p for k, v in value.items() if (p := _check(v, spec.spec, _join(where, k)))), "")
    for name, s in spec.items():
        if name not in value:
            if not isinstance(s, _Opt):
                return f"{_join(where, name)} is missing"
            continue
        problem = _check(value[name], s.spec if isinstance(s, _Opt) else s, _join(where, name))
        if problem:
            return problem
    return ""


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true or false"
    return {int: "a number", float: "a number", str: "a string", list: "a list", dict: "an object"}.get(
        type(value), type(value).__name__)


# -- on resume ----------------------------------------------------------------------------------------------------

def warn(message: str) -> None:
    warnings.warn(HgcaWarning(message), stacklevel=3)


def recorded(previous: dict | None) -> dict[str, dict]:
    """The earlier run's tile records by key (none when there is no trusted drive.json)."""
    return {t["key"]: t for t in (previous or {}).get("tiles", [])}


def check_cache(store, jobs: list[TileJob], previous: dict | None) -> dict[str, str]:
    """Check each of the plan's cached tiles (`DriveStore.check_entry`); a tile that fails is removed with its
    meshes, with one warning, so it is computed again. Returns the sha256 of every entry kept, by key."""
    records = recorded(previous)
    kept = {}
    for job in jobs:
        if not store.has(job.key):
            continue
        record, want = records.get(job.key, {}), made_from(job)
        if record.get("made_from", want) != want:       # the record is wrong, not (yet) the entry: set it aside
            warn(f"tile {job.index}: its record in drive.json names other inputs than the tile's key (edited by "
                 "hand?): checking its finished result on its own and writing its meshes again")
            record.pop("sha256", None)
        problem, digest = store.check_entry(job.key, want, job.settings.config.samples,
                                            record.get("sha256", {}).get(store.relative(store.entry(job.key))))
        if problem:
            warn(f"tile {job.index}: its finished result {store.entry(job.key)} {problem}: computing the tile again")
            store.discard(job.key)
            for mesh in store.tiles.glob(f"{job.index}_s*"):
                if MESH_NAME.match(mesh.name):
                    mesh.unlink(missing_ok=True)
        else:
            kept[job.key] = digest
    return kept


def checksums(store, key: str, outputs: list[str]) -> dict[str, str]:
    """The sha256 of a finished tile's files, by path in DIR: its cache entry and its tile meshes."""
    entry = store.entry(key)
    sums = {store.relative(entry): sha256_file(entry)}
    sums.update({o: sha256_file(store.root / o) for o in outputs})
    return sums


def check_meshes(store, tiles: list[dict], previous: dict | None, export: Callable[[int], None]) -> None:
    """Every finished tile's meshes are there and match their recorded sha256, else they are written again from
    its (checked) cache entry: missing or unrecorded ones silently (a run stopped while writing them, or no
    trusted drive.json), changed ones with a warning. Records their checksums in `tiles`."""
    records = recorded(previous)
    for t in tiles:
        if t["status"] != "done":
            continue
        sums = records.get(t["key"], {}).get("sha256", {})
        now = {o: _sha(store, o) for o in t["outputs"]}
        bad = [o for o in t["outputs"] if now[o] and sums.get(o) not in (None, now[o])]
        if bad:
            warn(f"tile {t['index']}: its mesh {', '.join(bad)} does not match its checksum in drive.json "
                 "(cut short or replaced?): writing it again from the finished tile")
        if bad or not all(now[o] and sums.get(o) == now[o] for o in t["outputs"]):
            export(t["index"])
            now = {o: _sha(store, o) for o in t["outputs"]}
        t["sha256"].update(now)


def _sha(store, relative: str) -> str:
    """sha256 of a file in DIR, '' when it is missing or unreadable."""
    try:
        return sha256_file(store.root / relative)
    except OSError:
        return ""


def sweep(store, doc: dict, previous: dict | None) -> None:
    """Remove the meshes under the drive's names that are not this plan's finished tiles: tile meshes of other
    tiles or formats, and the merged meshes when the earlier run's tiles were not these (another --size, seed,
    settings; or no trusted record). This run writes the merged meshes again when it ends."""
    tiles = doc["tiles"]
    done = {o for t in tiles if t["status"] == "done" for o in t["outputs"]}
    stale = [p for p in sorted(store.tiles.iterdir()) if MESH_NAME.match(p.name) and store.relative(p) not in done]
    same = previous is not None and [t["key"] for t in previous["tiles"]] == [t["key"] for t in tiles]
    ext = "." + doc["plan"]["mesh_format"]
    # without a trusted record the merged meshes go without a word of their own: nothing vouches for them, and
    # a rejected drive.json's warning said that the meshes are written again
    stale += [p for p in sorted(store.root.iterdir()) if DRIVE_NAME.match(p.name) and p.is_file()
              and (not same or p.suffix != ext)]
    if previous is None and all(DRIVE_NAME.match(p.name) for p in stale):
        for p in stale:
            p.unlink(missing_ok=True)
        return
    if not stale:
        return
    before = (previous or {}).get("plan", {})
    if previous is None:
        why = "no trusted drive.json says which tiles they hold"
    elif before.get("size") and before["size"] != doc["plan"]["size"]:
        why = (f"an earlier run planned {len(previous['tiles'])} tiles of {before['size'][0]:g} m here, this one "
               f"{len(tiles)} of {doc['plan']['size'][0]:g} m")
    elif before.get("mesh_format", doc["plan"]["mesh_format"]) != doc["plan"]["mesh_format"]:
        why = f"an earlier run wrote {before['mesh_format']} meshes, this one {doc['plan']['mesh_format']}"
    elif not same:
        why = "an earlier run made other tiles here (another seed, settings or inputs)"
    else:
        why = "their tiles' finished results are gone"
    names = ", ".join(store.relative(p) for p in stale[:4]) + (", ..." if len(stale) > 4 else "")
    warn(f"removing {len(stale)} mesh file(s) ({names}): {why}; only this plan's tiles are merged")
    for p in stale:
        p.unlink(missing_ok=True)
