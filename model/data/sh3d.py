"""Real furniture from Debian's ``sweethome3d-furniture`` package as dataset objects.

The package ships Sweet Home 3D furniture libraries (``.sh3f``): zip files of OBJ+MTL+textures
with a Java-properties catalogue, ``PluginFurnitureCatalog.properties``, giving each model's
name, creator and catalogue category, and a ``LICENSE.TXT`` (CC0 or CC-BY 3.0; the
attribution is kept in ``index.json``: ``name``, ``creator``, ``license``, ``library``).

- Fetching: the package is unpacked into ``$HYPNERF_CACHE/sweethome3d`` (default
  ``~/.cache/hypnerf/sweethome3d``) with ``apt-get download`` and ``dpkg -x``, which need no
  root and install nothing. A system-wide install (``/usr/share/sweethome3d/furniture``) is
  used when present.
- Categories: most catalogue entries carry no usable category, so the bundled
  ``sweethome3d_categories.tsv`` (library, model path, name, texture status; 65 chairs, 24 sofas,
  49 tables, classified by name and checked on renders) defines them.
- Models: each model's folder is extracted from its zip into ``<cache>/models/<library>/`` so
  the MTL and its textures resolve. Captions name the main colour and the catalogue name
  ("a brown armchair"). Sweet Home 3D models are Y-up with their front towards +Z;
  a catalogue ``modelRotation`` (3x3, rows listed first) is applied before the Y-up to Z-up
  turn, as Sweet Home 3D does. Units (cm) vanish in normalisation.
- Rendering, normalisation and the index are those of every other source (:mod:`model.data.build`).
"""

from __future__ import annotations

import csv
import logging
import re
import shutil
import subprocess
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from model.data.build import SourceObject, slug
from model.data.colours import default_caption
from model.data.imports import load_upright
from model.data.meshes import RenderMesh
from model.nerf.cache import cache_folder

log = logging.getLogger(__name__)

PACKAGE = "sweethome3d-furniture"
CATEGORIES = ("chair", "table", "sofa")
CATEGORY_FILE = Path(__file__).with_name("sweethome3d_categories.tsv")
CATALOGUE_FILE = "PluginFurnitureCatalog.properties"
LICENSE_FILE = "LICENSE.TXT"
FURNITURE_SUBDIR = Path("usr/share/sweethome3d/furniture")
SYSTEM_FURNITURE = Path("/") / FURNITURE_SUBDIR


class Sh3dError(RuntimeError):
    """The furniture package could not be obtained or read; the message says what to do."""


@dataclass
class CategoryRow:
    """One model of the category list: its library file, OBJ path inside it, name and texture status."""

    category: str
    library: str
    model: str
    name: str
    texture: str


# ---------------------------------------------------------------------------------------------
# The package


def cache_dir() -> Path:
    """Where the unpacked package and extracted models live."""
    return cache_folder("sweethome3d")


def _has_libraries(folder: Path) -> bool:
    return folder.is_dir() and any(folder.glob("*.sh3f"))


def fetch_package(cache: Path) -> Path:
    """Download the package with ``apt-get download`` and unpack it into ``cache`` with ``dpkg -x``."""
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache) as work:
        log.info("downloading %s with apt-get (about 110 MB)", PACKAGE)
        try:
            subprocess.run(["apt-get", "download", PACKAGE], cwd=work, check=True, capture_output=True, text=True)
        except FileNotFoundError:
            raise Sh3dError(
                f"apt-get is not available: download the {PACKAGE} .deb from packages.debian.org and "
                f"unpack it with `dpkg -x FILE.deb {cache}` (or set HYPNERF_CACHE to a folder holding it)"
            ) from None
        except subprocess.CalledProcessError as error:
            raise Sh3dError(
                f"`apt-get download {PACKAGE}` failed: {error.stderr.strip() or error}. Run `sudo apt-get update` "
                f"first (the package is in Debian main and Ubuntu universe), then try again"
            ) from None
        debs = sorted(Path(work).glob("*.deb"))
        if not debs:
            raise Sh3dError(f"`apt-get download {PACKAGE}` produced no .deb file in {work}; run `sudo apt-get update` and retry")
        staging = Path(work) / "unpacked"
        try:
            subprocess.run(["dpkg", "-x", str(debs[0]), str(staging)], check=True, capture_output=True, text=True)
        except (FileNotFoundError, subprocess.CalledProcessError) as error:
            raise Sh3dError(f"could not unpack {debs[0].name} with `dpkg -x` ({error}); install dpkg or unpack it by hand into {cache}") from None
        target = cache / FURNITURE_SUBDIR
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists():
            shutil.rmtree(target)
        # Move into place only once fully unpacked, so an interrupted download leaves no half cache.
        (staging / FURNITURE_SUBDIR).rename(target)
    log.info("unpacked %s into %s", PACKAGE, cache)
    return target


def furniture_dir(cache: Path | None = None, download: bool = True) -> Path:
    """The folder of ``.sh3f`` libraries: the cache, else a system install, else downloaded into the cache."""
    cache = cache_dir() if cache is None else Path(cache)
    for folder in (cache / FURNITURE_SUBDIR, SYSTEM_FURNITURE):
        if _has_libraries(folder):
            return folder
    if not download:
        raise Sh3dError(f"{PACKAGE} is not in {cache}; run `hypnerf data import-sh3d` once to download it")
    return fetch_package(cache)


# ---------------------------------------------------------------------------------------------
# Catalogues


_ESCAPES = {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}


def _unescape(text: str) -> str:
    out, i = [], 0
    while i < len(text):
        char = text[i]
        if char != "\\" or i + 1 == len(text):
            out.append(char)
            i += 1
            continue
        code = text[i + 1]
        if code == "u" and re.fullmatch(r"[0-9a-fA-F]{4}", text[i + 2 : i + 6]):
            out.append(chr(int(text[i + 2 : i + 6], 16)))
            i += 6
        else:
            out.append(_ESCAPES.get(code, code))
            i += 2
    return "".join(out)


def _logical_lines(text: str) -> Iterator[str]:
    """Physical lines joined where a line ends in an odd number of backslashes."""
    pending = ""
    for raw in text.splitlines():
        line = raw.lstrip() if pending else raw
        if not pending and line.lstrip()[:1] in ("#", "!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:
            pending += line[:-1]
            continue
        yield pending + line
        pending = ""
    if pending:
        yield pending


def parse_properties(data: bytes) -> dict[str, str]:
    """A Java ``.properties`` file (ISO-8859-1 with ``\\uXXXX`` escapes) as a dictionary."""
    properties = {}
    for line in _logical_lines(data.decode("iso-8859-1")):
        line = line.lstrip()
        if not line:
            continue
        # The key ends at the first unescaped '=', ':' or whitespace.
        match = re.match(r"((?:\\.|[^=:\s\\])*)\s*[=:]?\s*(.*)$", line, re.DOTALL)
        key, value = match.group(1), match.group(2)
        properties[_unescape(key)] = _unescape(value)
    return properties


def catalogue_entries(properties: dict[str, str]) -> dict[str, dict[str, str]]:
    """Catalogue entries (``key#N=value`` grouped by N) keyed by model path without its leading slash."""
    grouped: dict[str, dict[str, str]] = {}
    for key, value in properties.items():
        field_name, hash_sign, number = key.partition("#")
        if hash_sign and number.isdigit():
            grouped.setdefault(number, {})[field_name] = value
    return {entry["model"].lstrip("/"): entry for entry in grouped.values() if "model" in entry}


def licence_of(properties: dict[str, str], licence_text: str) -> tuple[str, str | None]:
    """The library's licence name and URL: the catalogue's ``license`` key, else read from ``LICENSE.TXT``."""
    urls = [u.rstrip(".,)") for u in re.findall(r"https?://\S+", licence_text)]
    # Prefer the licence's own address over the copyright holder's web site.
    url = next((u for u in urls if "creativecommons.org" in u), urls[0] if urls else None)
    if properties.get("license"):
        return re.sub(r"\s+", " ", properties["license"]).strip(), url
    named = re.search(r"(Creative Commons [^\n:]*?licen[cs]e)", licence_text)
    if named:
        return re.sub(r"\s+", " ", named.group(1)).strip(), url
    return "see LICENSE.TXT of the library", url


def model_rotation(entry: dict[str, str]) -> np.ndarray | None:
    """The entry's ``modelRotation`` as a 3x3 matrix (row-major, applied to column vectors), if any."""
    text = entry.get("modelRotation")
    if not text:
        return None
    values = [float(v) for v in text.split()]
    if len(values) != 9:
        raise Sh3dError(f"modelRotation {text!r} of {entry.get('id')} does not have 9 numbers")
    return np.array(values).reshape(3, 3)


@dataclass
class Library:
    """An opened ``.sh3f`` file with its catalogue and licence."""

    path: Path
    title: str
    licence: str
    licence_url: str | None
    entries: dict[str, dict[str, str]]

    @classmethod
    def open(cls, path: Path) -> Library:
        try:
            with zipfile.ZipFile(path) as archive:
                properties = parse_properties(archive.read(CATALOGUE_FILE))
                names = set(archive.namelist())
                text = archive.read(LICENSE_FILE).decode("utf-8", "replace") if LICENSE_FILE in names else ""
        except (zipfile.BadZipFile, KeyError, OSError) as error:
            raise Sh3dError(f"{path} is not a readable furniture library ({error}); delete it to download it again") from error
        licence, url = licence_of(properties, text)
        return cls(path, properties.get("name", path.stem), licence, url, catalogue_entries(properties))

    def extract_model(self, model: str, target_root: Path) -> Path:
        """Extract the model's folder (OBJ, MTL, textures) under ``target_root``; returns the OBJ path."""
        folder = model.rsplit("/", 1)[0] + "/" if "/" in model else ""
        target_root = target_root.resolve()
        obj = target_root / model
        marker = obj.with_name(obj.name + ".extracted")
        if marker.is_file():
            return obj
        with zipfile.ZipFile(self.path) as archive:
            members = [m for m in archive.namelist() if m.startswith(folder) and not m.endswith("/")]
            if model not in members:
                raise Sh3dError(f"{model} is not in {self.path.name}; the category list does not match this package version")
            for member in members:
                destination = (target_root / member).resolve()
                if not destination.is_relative_to(target_root):
                    raise Sh3dError(f"{self.path.name} holds an unsafe path {member!r}; refusing to extract it")
                destination.parent.mkdir(parents=True, exist_ok=True)
                destination.write_bytes(archive.read(member))
        marker.touch()
        return obj


# ---------------------------------------------------------------------------------------------
# Category rows and objects


def category_rows(category: str, table: Path = CATEGORY_FILE) -> list[CategoryRow]:
    """The rows of the category list for ``category``, in file order."""
    if category not in CATEGORIES:
        raise ValueError(f"category must be one of {CATEGORIES}, got {category!r}")
    with open(table, encoding="utf-8", newline="") as handle:
        lines = (line for line in handle if not line.startswith("#"))
        rows = [CategoryRow(**row) for row in csv.DictReader(lines, delimiter="\t")]
    return [row for row in rows if row.category == category]


def spread(rows: list, limit: int | None) -> list:
    """At most ``limit`` rows spread evenly over the list (so a small sample covers every library)."""
    if limit is None or limit >= len(rows):
        return list(rows)
    if limit < 1:
        raise ValueError(f"--limit must be at least 1, got {limit}")
    picks = np.linspace(0, len(rows) - 1, limit).round().astype(int)
    return [rows[i] for i in picks]


def object_id(row: CategoryRow) -> str:
    """``sh3d-<library>-<model folder>``, e.g. ``sh3d-scopia-chair4``."""
    folder = row.model.rsplit("/", 2)[-2] if row.model.count("/") >= 1 else Path(row.model).stem
    return f"sh3d-{slug(Path(row.library).stem)}-{slug(folder)}"


def _load_model(library: Library, row: CategoryRow, entry: dict[str, str], models_dir: Path) -> tuple[RenderMesh, dict]:
    obj = library.extract_model(row.model, models_dir / Path(row.library).stem)
    mesh, texture = load_upright(obj, "y", rotation=model_rotation(entry))
    if texture != row.texture:
        log.warning("%s: texture status %s differs from the category list's %s", row.model, texture, row.texture)
    noun = entry.get("name", row.name)
    return mesh, {"texture": texture, "caption": default_caption(mesh, noun), "noun": noun}


def sh3d_objects(
    category: str, limit: int | None = None, cache: Path | None = None, table: Path = CATEGORY_FILE
) -> Iterator[SourceObject]:
    """Objects of one category of ``table`` from the furniture package (downloaded on first use)."""
    rows = spread(category_rows(category, table), limit)
    cache = cache_dir() if cache is None else Path(cache)
    furniture = furniture_dir(cache)
    libraries: dict[str, Library] = {}
    for row in rows:
        if row.library not in libraries:
            path = furniture / row.library
            if not path.is_file():
                raise Sh3dError(f"{path} is missing; delete {cache} to download {PACKAGE} again")
            libraries[row.library] = Library.open(path)
        library = libraries[row.library]
        entry = library.entries.get(row.model)
        if entry is None:
            raise Sh3dError(f"{row.model} is not in the catalogue of {row.library}; the category list does not match this package version")
        name = entry.get("name", row.name)
        extra = {
            "source": PACKAGE,
            "library": library.title,
            "model": row.model,
            "catalog_id": entry.get("id", ""),
            "name": name,
            "creator": entry.get("creator", ""),
            "license": library.licence,
        }
        if library.licence_url:
            extra["license_url"] = library.licence_url
        yield SourceObject(
            id=object_id(row),
            category=category,
            caption="",
            load=partial(_load_model, library, row, entry, cache / "models"),
            extra=extra,
        )
