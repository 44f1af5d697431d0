"""The bundle's table of contents: ``manifest.json`` with the format version, the sha256 and size
of every other file, the configs, the training data's attribution and the optional components.

Hashes use the standard library's ``hashlib`` (sha256, streamed in 1 MiB blocks). Verification
reports the first problem it finds as a :class:`BundleError` that names the file and says what to
do, so a tampered, truncated or missing file is never loaded.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

from model.denoise.io import DENOISER_META, DENOISER_WEIGHTS
from model.prior.query import QUERY_META, QUERY_WEIGHTS

log = logging.getLogger(__name__)

BUNDLE_FORMAT = 1
"""The bundle layout this code writes and the newest it reads."""

MANIFEST = "manifest.json"
INSTANCES = "instances.json"
WEIGHTS = "weights.safetensors"
HYPERNET_ONNX = "hypernet.onnx"
QUERY_ONNX = "query.onnx"
EMBEDDINGS = "embeddings.npy"
COMPONENT_FILES = {
    "hypernet": (WEIGHTS, HYPERNET_ONNX, INSTANCES),
    # the query network's and the denoiser's own files keep the names their runs give them
    "query": (QUERY_WEIGHTS, QUERY_META, QUERY_ONNX, EMBEDDINGS),
    "denoiser": (DENOISER_WEIGHTS, DENOISER_META),
}
"""The files each component needs; the manifest's ``components`` says which are present."""
SHAPE_INPUT = "shape"
COLOR_INPUT = "color"
EMBEDDING_INPUT = "embedding"
"""Tensor names of the ONNX graphs: the hypernetwork reads ``shape`` and ``color`` (and emits the
NeRF parameters by their names); the query network reads ``embedding`` and emits ``shape`` and ``color``."""

_BLOCK = 1 << 20
_REMEDY = "re-export it with `hypnerf export` or download it again"


class BundleError(ValueError):
    """A bundle file is tampered, truncated or missing, or the bundle's format is newer than this
    code reads; the message names the file and says what to do."""


def file_digest(path: Path) -> str:
    """sha256 hex of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def file_record(path: Path) -> dict:
    """``{"sha256", "bytes"}`` of one file, as the manifest lists it."""
    return {"sha256": file_digest(path), "bytes": path.stat().st_size}


def read_manifest(folder: Path) -> tuple[dict, str]:
    """The parsed manifest of a bundle folder and the bundle's digest (sha256 hex of the manifest's bytes).

    Refuses a missing or malformed manifest and a format newer than :data:`BUNDLE_FORMAT`.
    """
    path = Path(folder) / MANIFEST
    if not Path(folder).is_dir():
        raise BundleError(f"{folder} is not a bundle folder; make one with `hypnerf export --run RUN --out {folder}`")
    if not path.is_file():
        raise BundleError(f"{path} is missing, so {folder} is not a complete bundle; {_REMEDY}")
    raw = path.read_bytes()
    try:
        manifest = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise BundleError(f"{path} is not valid JSON ({error}); {_REMEDY}") from error
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
        raise BundleError(f"{path} lacks its 'files' table; {_REMEDY}")
    version = manifest.get("format")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise BundleError(f"{path} has no valid 'format' version (got {version!r}); {_REMEDY}")
    if version > BUNDLE_FORMAT:
        raise BundleError(
            f"{folder} is a format-{version} bundle; this hypnerf reads bundle formats up to {BUNDLE_FORMAT}: "
            f"upgrade hypnerf to a release that reads format {version}, or export the bundle again with this one"
        )
    return manifest, hashlib.sha256(raw).hexdigest()


def verify_files(folder: Path, manifest: dict, *, hashes: bool = True) -> None:
    """Check that the manifest lists every file its components need and that every listed file
    exists with its recorded size and (with ``hashes``) sha256."""
    files = manifest["files"]
    components = ["hypernet", *(c for c in manifest.get("components", []) if c != "hypernet")]
    unlisted_needed = [name for c in components for name in COMPONENT_FILES.get(c, ()) if name not in files]
    if unlisted_needed:
        raise BundleError(f"{Path(folder) / MANIFEST} does not list {', '.join(unlisted_needed)}, which its components need; {_REMEDY}")
    for name, record in files.items():
        path = Path(folder) / name
        if Path(name).name != name or name == MANIFEST:
            raise BundleError(f"{Path(folder) / MANIFEST} lists {name!r}, which is not a plain file name of the bundle; {_REMEDY}")
        if not path.is_file():
            raise BundleError(f"{path} is missing from the bundle; {_REMEDY}")
        size = path.stat().st_size
        if size != record.get("bytes"):
            raise BundleError(f"{path} has {size} bytes but the manifest records {record.get('bytes')} (truncated or altered); {_REMEDY}")
        if hashes and file_digest(path) != record.get("sha256"):
            raise BundleError(f"{path} does not match its sha256 in the manifest (altered or corrupted); {_REMEDY}")
    unlisted = sorted(p.name for p in Path(folder).iterdir() if p.name != MANIFEST and p.name not in files)
    if unlisted:
        log.warning("%s holds files the manifest does not list (ignored): %s", folder, ", ".join(unlisted))
