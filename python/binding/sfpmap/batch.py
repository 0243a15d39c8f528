"""``python -m sfpmap.batch MANIFEST --out PREFIX``: many places' COLMAP models into sfpmap maps
and a catalog, on a Ray cluster (``pip install 'sfpmap[ray]'``).

MANIFEST is JSON lines, one place each (a local file or an ``s3://``/``https://`` URL)::

    {"place": "hall-a", "colmap": "s3://in/hall-a/sparse", "database": "s3://in/hall-a/database.db",
     "variants": ["l2s", "pq8"], "budget": "2MB"}

``place`` (the output folder's name), ``colmap`` (a model folder: cameras, images, points3D as
``.bin`` or ``.txt``) and ``database`` (a SIFT or other-feature map) or ``images`` (an SFP map
from the images) are paths or URLs, as the CLI's flags; a relative path is relative to the
manifest's folder. ``variants`` are slices written beside the map (``l2s``: level 2, short;
``l2``: level 2; ``pq8``: every level in 8-byte PQ codes; ``l2s-pq8``; ``-min`` appended:
``--minimal``), ``budget`` one more slice cut to that many bytes (``slice --budget``). Instead
of a manifest, an ``s3://`` prefix ending in ``/`` lists its places: every ``<prefix><place>/``
holding ``sparse/`` and ``database.db`` or ``images/``.

Each place is one Ray task (one CPU; ``--cpus-per-place``): list and fetch its inputs (objects
streamed to a work folder, never held whole), convert, slice, then store the outputs under
``PREFIX/<place>/`` (``map.sfpm``, ``<variant>.sfpm``, ``budget-<size>.sfpm``). PREFIX is a
folder or an ``s3://`` prefix; ``PREFIX/catalog.sfpc`` then catalogs the places (each by its
first variant without PQ codes, else its map: a catalog reads f16 descriptors).

Exactly once: every output appears complete or not at all (an S3 PUT or multipart upload
stored only whole, its SHA-256 checked by the server; in a folder, a rename within the folder)
and records the place's input fingerprint and options in its provenance
(``provenance.parameters.job``, or in ``history`` for a slice). A place whose outputs all carry
the fingerprint it has now is skipped, so a crashed job resumes by running it again. Ray
retries a task whose worker or node is lost; a place that fails (a missing or damaged model, a
403) is a row of the report with its one-line error and stops no other. Exit code 1 when any
place failed.

The driver's ``AWS_*`` and ``SFPMAP_*`` variables are passed to the tasks. One job per PREFIX at
a time.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import sys
import tempfile
import time
from typing import Any, Dict, List, Optional, Tuple

from . import Error as _SfpmapError
from . import _sfpmap
from . import convert as _convert
from . import slice as _slice

__all__ = ["main", "read_manifest", "parse_variant", "parse_size", "run_place"]

KEYS = ("place", "colmap", "database", "images", "variants", "budget")
MODEL_STEMS = ("cameras", "images", "points3D", "rigs", "frames")
REQUIRED_STEMS = ("cameras", "images", "points3D")
PLACE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}\Z")
VARIANT = re.compile(r"(?:l(?P<level>\d{1,5})(?P<short>s?))?(?:-?pq(?P<pq>\d{1,4}))?(?P<min>-?min)?\Z")
SIZE = re.compile(r"\s*(?P<number>\d+(?:\.\d+)?)\s*(?P<unit>[kKMGT]?i?B?)\s*\Z")
UNITS = {"": 1, "B": 1, "kB": 10**3, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
         "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}
MAP_NAME = "map.sfpm"
CATALOG_NAME = "catalog.sfpc"
# A local PREFIX's work folder: outputs are renamed from it into place (same file system).
TMP_NAME = ".sfpmap-batch-tmp"
# One input object at most (the work folder holds it; memory holds a piece at a time).
MAX_OBJECT_BYTES = 1 << 40
MAX_LISTED = 1_000_000
STAGES = ("list", "fetch", "convert", "slice", "store")


def is_url(location: str) -> bool:
    return location.startswith(("s3://", "http://", "https://"))


def one_line(e: BaseException) -> str:
    text = str(e) or type(e).__name__
    return " ".join(text.split())


def parse_size(value: Any) -> int:
    """A byte count: an int, or text such as ``2MB``, ``500kB``, ``1.5MiB``."""
    if isinstance(value, bool):
        raise ValueError(f"{value!r} is not a size such as 2MB, 500kB or 1.5MiB")
    if isinstance(value, int):
        if value <= 0:
            raise ValueError(f"{value} bytes: a budget is at least 1 byte")
        return value
    m = SIZE.match(value) if isinstance(value, str) else None
    if m is None or m["unit"] not in UNITS:
        raise ValueError(f"{value!r} is not a size such as 2MB, 500kB or 1.5MiB")
    n = int(float(m["number"]) * UNITS[m["unit"]])
    if n <= 0:
        raise ValueError(f"{value!r}: a budget is at least 1 byte")
    return n


def parse_variant(name: Any) -> Dict[str, Any]:
    """What a variant name asks ``slice`` for: ``levels`` (None: every level), ``short``, ``pq``,
    ``minimal``."""
    m = VARIANT.match(name) if isinstance(name, str) else None
    if m is None or not name or (m["level"] is None and m["pq"] is None and m["min"] is None):
        raise ValueError(
            f"variant {name!r}: l<level>[s][-pq<M>][-min] or pq<M>[-min] (e.g. l2s, l2, pq8, l2s-pq8)"
        )
    return {
        "levels": None if m["level"] is None else [int(m["level"])],
        "short": bool(m["short"]),
        "pq": None if m["pq"] is None else int(m["pq"]),
        "minimal": m["min"] is not None,
    }


# ---------------------------------------------------------------------------------------------
# The manifest


def _resolve(value: Any, key: str, base: str) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{key}: a path or URL")
    if is_url(value) or os.path.isabs(value) or is_url(base):
        if is_url(base) and not is_url(value) and not os.path.isabs(value):
            return base.rstrip("/") + "/" + value
        return value
    return os.path.normpath(os.path.join(base, value))


def _place(obj: Any, line: int, base: str) -> Dict[str, Any]:
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    unknown = sorted(set(obj) - set(KEYS))
    if unknown:
        raise ValueError(f"unknown key {unknown[0]!r} (known: {', '.join(KEYS)})")
    name = obj.get("place")
    if not isinstance(name, str) or not PLACE_NAME.match(name):
        raise ValueError(f"place {name!r}: 1 to 128 of A-Z a-z 0-9 . _ -, not starting with . _ -")
    if "colmap" not in obj:
        raise ValueError("no colmap: the place's COLMAP model folder")
    if ("database" in obj) == ("images" in obj):
        raise ValueError("give database (a feature map) or images (an SFP map), one of them")
    variants = obj.get("variants", [])
    if not isinstance(variants, list):
        raise ValueError("variants: a list such as [\"l2s\", \"pq8\"]")
    for v in variants:
        parse_variant(v)
    if len(set(variants)) != len(variants):
        raise ValueError("variants: a variant listed twice")
    budget = obj.get("budget")
    return {
        "line": line,
        "place": name,
        "colmap": _resolve(obj["colmap"], "colmap", base),
        "database": _resolve(obj["database"], "database", base) if "database" in obj else None,
        "images": _resolve(obj["images"], "images", base) if "images" in obj else None,
        "variants": list(variants),
        "budget": None if budget is None else [parse_size(budget), str(budget).replace(" ", "")],
    }


def _fail_row(place: str, error: str, line: Optional[int] = None) -> Dict[str, Any]:
    return {"place": place, "line": line, "status": "failed", "error": error, "bytes_in": 0,
            "bytes_out": 0, "seconds": {}, "outputs": []}


def read_manifest(manifest: str) -> Tuple[List[Dict[str, Any]], List[Dict[str, Any]]]:
    """The places of ``manifest`` (a JSON lines file or URL, or an ``s3://`` prefix ending in
    ``/``) and a failed row for each line that is not one."""
    if manifest.startswith("s3://") and manifest.endswith("/"):
        return _list_places(manifest), []
    if is_url(manifest):
        with tempfile.TemporaryDirectory(prefix="sfpmap-manifest-") as tmp:
            path = os.path.join(tmp, "manifest.jsonl")
            _sfpmap.object_download(manifest, path, 64 << 20)
            text = _read_text(path, manifest)
        base = manifest.rsplit("/", 1)[0]
    else:
        text = _read_text(manifest, manifest)
        base = os.path.dirname(os.path.abspath(manifest))
    places: List[Dict[str, Any]] = []
    failed: List[Dict[str, Any]] = []
    seen = set()
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        where = f"{manifest}: line {number}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as e:
            failed.append(_fail_row(f"line {number}", f"{where}: not JSON ({e.msg})", number))
            continue
        name = obj.get("place") if isinstance(obj, dict) and isinstance(obj.get("place"), str) else f"line {number}"
        try:
            place = _place(obj, number, base)
        except ValueError as e:
            failed.append(_fail_row(name, f"{where}: {e}", number))
            continue
        if place["place"] in seen:
            failed.append(_fail_row(name, f"{where}: place {name!r} is listed twice", number))
            continue
        seen.add(place["place"])
        places.append(place)
    return places, failed


def _read_text(path: str, shown: str) -> str:
    try:
        with open(path, "rb") as f:
            data = f.read((64 << 20) + 1)
    except OSError as e:
        raise SystemExit(f"error: {shown}: {e.strerror or e}")
    if len(data) > 64 << 20:
        raise SystemExit(f"error: {shown}: a manifest over 64 MiB")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise SystemExit(f"error: {shown}: not UTF-8 text")


def _list_places(prefix: str) -> List[Dict[str, Any]]:
    places: Dict[str, Dict[str, Any]] = {}
    for url, _size, _etag in _sfpmap.object_list(prefix, MAX_LISTED):
        rest = url[len(prefix):]
        parts = rest.split("/")
        if len(parts) < 2 or not PLACE_NAME.match(parts[0]):
            continue
        p = places.setdefault(parts[0], {"sparse": False, "database": False, "images": False})
        if parts[1] in ("sparse", "database.db", "images") and (parts[1] == "database.db") == (len(parts) == 2):
            p[parts[1].split(".")[0]] = True
    found = []
    for line, (name, p) in enumerate(sorted(places.items()), 1):
        if not p["sparse"] or not (p["database"] or p["images"]):
            continue
        found.append({
            "line": line, "place": name, "colmap": f"{prefix}{name}/sparse",
            "database": f"{prefix}{name}/database.db" if p["database"] else None,
            "images": None if p["database"] else f"{prefix}{name}/images",
            "variants": [], "budget": None,
        })
    return found


# ---------------------------------------------------------------------------------------------
# One place (a Ray task)


def _listed(prefix: str) -> List[Tuple[str, int, str]]:
    """The objects under ``prefix`` with their ETags (a HEAD each where the listing gave none:
    a fingerprint of sizes alone would miss a rewritten object of the same length)."""
    found = []
    for url, size, etag in _sfpmap.object_list(prefix, MAX_LISTED):
        if etag is None:
            head = _sfpmap.object_head(url)
            etag = head[2] if head is not None else None
        found.append((url, size, etag or ""))
    return found


def _inputs(place: Dict[str, Any]) -> List[Tuple[str, str, int, str]]:
    """Every input file: (name in the work folder, path or URL, size, version: ETag or mtime)."""
    out: List[Tuple[str, str, int, str]] = []
    colmap = place["colmap"]
    if is_url(colmap):
        base = colmap.rstrip("/")
        if colmap.startswith("s3://"):
            listed = _listed(base)
            model = [(u, s, e) for u, s, e in listed if "/" not in u[len(base) + 1:]
                     and u.rsplit("/", 1)[1].split(".")[0] in MODEL_STEMS
                     and u.rsplit(".", 1)[-1] in ("bin", "txt")]
        else:
            model = []
            for ext in ("bin", "txt"):
                heads = [_sfpmap.object_head(f"{base}/{stem}.{ext}") for stem in MODEL_STEMS]
                if all(h is not None for h in heads[:3]):
                    model = [h for h in heads if h is not None]
                    break
        for url, size, etag in model:
            out.append(("colmap/" + url.rsplit("/", 1)[1], url, size, etag or ""))
    else:
        if not os.path.isdir(colmap):
            raise FileNotFoundError(f"{colmap}: no such folder (the COLMAP model)")
        for name in sorted(os.listdir(colmap)):
            stem, _, ext = name.partition(".")
            path = os.path.join(colmap, name)
            if stem in MODEL_STEMS and ext in ("bin", "txt") and os.path.isfile(path):
                st = os.stat(path)
                out.append(("colmap/" + name, path, st.st_size, str(st.st_mtime_ns)))
    stems = {n.split("/")[1].split(".")[0] for n, *_ in out}
    if not all(s in stems for s in REQUIRED_STEMS):
        raise FileNotFoundError(f"{colmap}: no COLMAP model (cameras, images and points3D, .bin or .txt)")
    if place["database"] is not None:
        db = place["database"]
        if is_url(db):
            head = _sfpmap.object_head(db)
            if head is None:
                raise FileNotFoundError(f"{db}: no such object (the database)")
            out.append(("database.db", db, head[1], head[2] or ""))
        else:
            st = os.stat(db)
            out.append(("database.db", db, st.st_size, str(st.st_mtime_ns)))
    if place["images"] is not None:
        images = place["images"]
        if images.startswith(("http://", "https://")):
            raise ValueError(f"{images}: images from a web server cannot be listed: use s3:// or a folder")
        if is_url(images):
            base = images.rstrip("/")
            for url, size, etag in _listed(base):
                rel = url[len(base) + 1:]
                if any(part in ("", ".", "..") for part in rel.split("/")):
                    raise ValueError(f"{url}: an image name with an empty, . or .. part")
                out.append(("images/" + rel, url, size, etag or ""))
        else:
            if not os.path.isdir(images):
                raise FileNotFoundError(f"{images}: no such folder (the images)")
            for root, dirs, files in os.walk(images):
                dirs.sort()
                for f in sorted(files):
                    path = os.path.join(root, f)
                    st = os.stat(path)
                    out.append(("images/" + os.path.relpath(path, images), path, st.st_size, str(st.st_mtime_ns)))
    return out


def _options(place: Dict[str, Any]) -> Dict[str, Any]:
    return {"kind": "sfp" if place["images"] is not None else "features",
            "variants": place["variants"],
            "budget": None if place["budget"] is None else place["budget"][0]}


def _fingerprint(inputs: List[Tuple[str, str, int, str]], options: Dict[str, Any]) -> str:
    text = json.dumps({"inputs": [[n, s, v] for n, _, s, v in inputs], "options": options},
                      sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _output_names(place: Dict[str, Any]) -> List[str]:
    names = [MAP_NAME] + [f"{v}.sfpm" for v in place["variants"]]
    if place["budget"] is not None:
        names.append(f"budget-{place['budget'][1]}.sfpm")
    return names


def _join(prefix: str, *parts: str) -> str:
    if is_url(prefix):
        return prefix.rstrip("/") + "/" + "/".join(parts)
    return os.path.join(prefix, *parts)


def job_of(metadata: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The batch record a map carries: its operation's ``job``, else the latest in its
    history (a slice of a converted map)."""
    provenance = metadata.get("provenance") or {}
    job = (provenance.get("parameters") or {}).get("job")
    if isinstance(job, dict):
        return job
    for entry in reversed(provenance.get("history") or []):
        job = (entry.get("parameters") or {}).get("job") if isinstance(entry, dict) else None
        if isinstance(job, dict):
            return job
    return None


def _stored_fingerprint(location: str) -> Optional[str]:
    if is_url(location):
        if _sfpmap.object_head(location) is None:
            return None
    elif not os.path.isfile(location):
        return None
    try:
        job = job_of(json.loads(_sfpmap.map_metadata(location)))
    except _SfpmapError:
        return None  # not a readable map: made again
    return None if job is None else job.get("fingerprint")


def _node() -> str:
    try:
        import ray

        return ray.get_runtime_context().get_node_id()
    except Exception:  # outside Ray (a direct call)
        return ""


def run_place(place: Dict[str, Any], out: str, work_root: Optional[str] = None,
              threads: int = 1, force: bool = False) -> Dict[str, Any]:
    """Converts, slices and stores one place; returns its report row (never raises for the
    place's own errors: they are the row's ``error``)."""
    row = _fail_row(place["place"], "", place.get("line"))
    row["node"] = _node()
    seconds: Dict[str, float] = {}
    row["seconds"] = seconds
    work = None
    try:
        began = time.perf_counter()
        inputs = _inputs(place)
        options = _options(place)
        fingerprint = _fingerprint(inputs, options)
        names = _output_names(place)
        finals = [_join(out, place["place"], n) for n in names]
        row["fingerprint"] = fingerprint
        row["outputs"] = finals
        # A catalog reads f16 descriptors: the first variant without PQ codes, else the map.
        plain = [i for i, v in enumerate(place["variants"], 1) if parse_variant(v)["pq"] is None]
        row["catalog_map"] = finals[plain[0] if plain else 0]
        row["bytes_in"] = sum(s for _, _, s, _ in inputs)
        if not force and all(_stored_fingerprint(f) == fingerprint for f in finals):
            seconds["list"] = time.perf_counter() - began
            row.update(status="skipped", error=None, bytes_in=0)
            return row
        seconds["list"] = time.perf_counter() - began

        if is_url(out):
            work = tempfile.mkdtemp(prefix=f"sfpmap-batch-{place['place']}-", dir=work_root)
        else:
            tmp = os.path.join(out, TMP_NAME)
            os.makedirs(tmp, exist_ok=True)
            work = tempfile.mkdtemp(prefix=f"{place['place']}-", dir=tmp)
        began = time.perf_counter()
        local: Dict[str, str] = {}
        for name, location, size, _version in inputs:
            if is_url(location):
                dest = os.path.join(work, "in", name)
                os.makedirs(os.path.dirname(dest), exist_ok=True)
                _sfpmap.object_download(location, dest, MAX_OBJECT_BYTES)
                local[name] = dest
            else:
                local[name] = location
        colmap = place["colmap"] if not is_url(place["colmap"]) else os.path.join(work, "in", "colmap")
        database = None
        if place["database"] is not None:
            database = local["database.db"]
        images = None
        if place["images"] is not None:
            images = place["images"] if not is_url(place["images"]) else os.path.join(work, "in", "images")
        seconds["fetch"] = time.perf_counter() - began

        began = time.perf_counter()
        job = {"place": place["place"], "fingerprint": fingerprint, "options": options,
               "inputs": {"colmap": place["colmap"], "database": place["database"],
                          "images": place["images"], "files": len(inputs),
                          "bytes": row["bytes_in"]}}
        made = os.path.join(work, MAP_NAME)
        _convert(colmap, database=database, images=images, out=made, job=job, threads=threads)
        seconds["convert"] = time.perf_counter() - began

        began = time.perf_counter()
        files = [made]
        all_levels = None
        for variant in place["variants"]:
            v = parse_variant(variant)
            if v["levels"] is None and all_levels is None:
                meta = json.loads(_sfpmap.map_metadata(made))
                all_levels = [lv["level"] for lv in meta.get("levels", [])]
            path = os.path.join(work, f"{variant}.sfpm")
            _slice(made, v["levels"] or all_levels, v["short"], out=path, minimal=v["minimal"], pq=v["pq"])
            files.append(path)
        if place["budget"] is not None:
            path = os.path.join(work, names[-1])
            _slice(made, [], out=path, budget=place["budget"][0])
            files.append(path)
        seconds["slice"] = time.perf_counter() - began

        began = time.perf_counter()
        made_bytes = sum(os.path.getsize(f) for f in files)
        _store(files, finals, out, place["place"])
        seconds["store"] = time.perf_counter() - began
        row["bytes_out"] = made_bytes
        row.update(status="done", error=None)
    except (_SfpmapError, OSError, ValueError) as e:
        row["error"] = one_line(e)
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    return row


def _store(files: List[str], finals: List[str], out: str, place: str) -> None:
    """Puts each output in place, the map last. An object appears whole or not at all; on an
    error, the objects this call stored are removed again (the place is made again next run)."""
    order = list(range(1, len(files))) + [0]
    if not is_url(out):
        folder = os.path.join(out, place)
        os.makedirs(folder, exist_ok=True)
        for i in order:
            os.replace(files[i], finals[i])
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        return
    stored: List[str] = []
    try:
        for i in order:
            _sfpmap.object_upload(files[i], finals[i])
            stored.append(finals[i])
    except _SfpmapError:
        for url in stored:
            try:
                _sfpmap.object_delete(url)
            except _SfpmapError:
                pass
        raise


# ---------------------------------------------------------------------------------------------
# The job


def _catalog(rows: List[Dict[str, Any]], out: str, work_root: Optional[str]) -> Dict[str, Any]:
    """``PREFIX/catalog.sfpc`` over the places done or skipped; not written again when the one
    there lists the same places at the same fingerprints."""
    ok = sorted((r for r in rows if r["status"] in ("done", "skipped")), key=lambda r: r["place"])
    target = _join(out, CATALOG_NAME)
    if not ok:
        return {"status": "none", "places": 0}
    locations = [r["catalog_map"] if is_url(out) else os.path.relpath(r["catalog_map"], out) for r in ok]
    record = {"places": [[r["place"], r["fingerprint"], loc] for r, loc in zip(ok, locations)]}
    fingerprint = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()
    began = time.perf_counter()
    if _stored_fingerprint(target) == fingerprint:
        return {"status": "unchanged", "places": len(ok), "url": target,
                "seconds": time.perf_counter() - began}
    job = json.dumps({"fingerprint": fingerprint, "places": len(ok)})
    names = [r["place"] for r in ok]
    if is_url(out):
        with tempfile.TemporaryDirectory(prefix="sfpmap-catalog-", dir=work_root) as tmp:
            path = os.path.join(tmp, CATALOG_NAME)
            report = json.loads(_sfpmap.build_catalog(locations, names, out=path, job=job))
            _sfpmap.object_upload(path, target)
    else:
        maps = [r["catalog_map"] for r in ok]
        report = json.loads(_sfpmap.build_catalog(maps, names, out=target, locations=locations,
                                                  job=job, force=True))
    return {"status": "written", "places": len(ok), "url": target, "bytes": report["bytes"],
            "seconds": time.perf_counter() - began}


def _table(report: Dict[str, Any]) -> str:
    lines = [f"{'place':<24} {'status':<8} {'MB in':>8} {'MB out':>8} "
             + " ".join(f"{s:>8}" for s in STAGES) + "  error"]
    for r in report["rows"]:
        secs = " ".join(f"{r['seconds'][s]:8.2f}" if s in r["seconds"] else f"{'':>8}" for s in STAGES)
        lines.append(f"{r['place'][:24]:<24} {r['status']:<8} {r['bytes_in'] / 1e6:8.2f} "
                     f"{r['bytes_out'] / 1e6:8.2f} {secs}  {r.get('error') or ''}")
    p = report["places"]
    lines.append(f"{p['total']} places: {p['done']} done, {p['skipped']} skipped, {p['failed']} failed; "
                 f"{report['bytes_in'] / 1e6:.1f} MB in, {report['bytes_out'] / 1e6:.1f} MB out, "
                 f"{report['seconds']['wall']:.1f} s ({report['places_per_minute']:.1f} places/min)")
    c = report["catalog"]
    lines.append(f"catalog: {c['status']}" + (f" ({c['url']}, {c['places']} places)" if "url" in c else "")
                 + (f": {c['error']}" if "error" in c else ""))
    return "\n".join(lines)


def _write_report(path: str, report: Dict[str, Any]) -> None:
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".report-", dir=folder)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(report, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _passed_env() -> Dict[str, str]:
    return {k: v for k, v in os.environ.items() if k.startswith(("AWS_", "SFPMAP_"))}


def run(manifest: str, out: str, *, address: Optional[str] = None, cpus_per_place: int = 1,
        retries: int = 3, work_dir: Optional[str] = None, force: bool = False,
        progress: Any = None) -> Dict[str, Any]:
    """The job: every place of ``manifest`` as a Ray task, then the catalog. Returns the report
    (``rows`` per place, totals, ``catalog``). ``progress(done, total, row)`` is called as each
    place ends."""
    try:
        import ray
    except ImportError:
        raise SystemExit("error: sfpmap.batch runs on Ray: pip install 'sfpmap[ray]'")
    began = time.perf_counter()
    places, rows = read_manifest(manifest)
    if not is_url(out):
        out = os.path.abspath(out)
        os.makedirs(out, exist_ok=True)
        shutil.rmtree(os.path.join(out, TMP_NAME), ignore_errors=True)
    elif not out.startswith("s3://"):
        raise SystemExit(f"error: {out}: outputs go to a folder or an s3:// prefix")
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": _passed_env()}, logging_level="ERROR")
    task = ray.remote(num_cpus=cpus_per_place, max_retries=retries, retry_exceptions=False)(run_place)
    pending = {task.remote(p, out, work_dir, cpus_per_place, force): p for p in places}
    total = len(places) + len(rows)
    for done, row in enumerate(rows, 1):
        if progress:
            progress(done, total, row)
    waiting = list(pending)
    while waiting:
        ready, waiting = ray.wait(waiting, num_returns=1)
        for ref in ready:
            try:
                row = ray.get(ref)
            except ray.exceptions.RayError as e:
                p = pending[ref]
                row = _fail_row(p["place"], f"the task failed {retries + 1} times: {one_line(e)}"[:2000], p["line"])
            rows.append(row)
            if progress:
                progress(len(rows), total, row)
    rows.sort(key=lambda r: (r["line"] or 0, r["place"]))
    try:
        catalog = _catalog(rows, out, work_dir)
    except (_SfpmapError, OSError) as e:
        catalog = {"status": "failed", "error": one_line(e)}
    if not is_url(out):
        shutil.rmtree(os.path.join(out, TMP_NAME), ignore_errors=True)
    wall = time.perf_counter() - began
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed")}
    stage_sums = {s: round(sum(r["seconds"].get(s, 0.0) for r in rows), 3) for s in STAGES}
    return {
        "manifest": manifest, "out": out, "address": address,
        "places": {"total": len(rows), **counts},
        "bytes_in": sum(r["bytes_in"] for r in rows),
        "bytes_out": sum(r["bytes_out"] for r in rows),
        "seconds": {"wall": wall, **stage_sums},
        "places_per_minute": (counts["done"] * 60.0 / wall) if wall > 0 else 0.0,
        "catalog": catalog,
        "rows": rows,
    }


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sfpmap.batch",
        description="Convert and slice many places' COLMAP models into sfpmap maps and a catalog, on Ray.")
    parser.add_argument("manifest", help="JSON lines, one place each (file or URL), or an s3:// prefix ending in /")
    parser.add_argument("--out", required=True, help="output folder or s3:// prefix")
    parser.add_argument("--address", help="a Ray cluster (default: RAY_ADDRESS, else a local Ray)")
    parser.add_argument("--report", help="write the report (JSON) here")
    parser.add_argument("--cpus-per-place", type=int, default=1, help="CPUs (and threads) per place (default 1)")
    parser.add_argument("--retries", type=int, default=3, help="retries of a task whose worker is lost (default 3)")
    parser.add_argument("--work-dir", help="where an s3:// job fetches inputs (default: the system's temp folder)")
    parser.add_argument("--force", action="store_true", help="make every place again, whatever is stored")
    parser.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    args = parser.parse_args(argv)
    if args.cpus_per_place < 1 or args.retries < 0:
        parser.error("--cpus-per-place is at least 1 and --retries at least 0")

    def progress(done: int, total: int, row: Dict[str, Any]) -> None:
        if not args.quiet and not args.json:
            tail = f": {row['error']}" if row["status"] == "failed" else ""
            print(f"[{done}/{total}] {row['place']} {row['status']}{tail}", file=sys.stderr, flush=True)

    # Ray prints its own notices (a node lost, a task retried) to standard output: they go to
    # standard error while the job runs, so standard output holds the table or JSON alone.
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        report = run(args.manifest, args.out, address=args.address, cpus_per_place=args.cpus_per_place,
                     retries=args.retries, work_dir=args.work_dir, force=args.force, progress=progress)
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
    if args.report:
        _write_report(args.report, report)
    if args.json:
        print(json.dumps(report))
    elif not args.quiet:
        print(_table(report))
    failed = report["places"]["failed"] > 0 or report["catalog"]["status"] == "failed"
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
