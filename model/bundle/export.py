"""Export a trained prior run to a bundle: the folder the service loads.

A bundle holds ``weights.safetensors`` (the hypernetwork's state dict as the prior stores it:
codebooks, heads, shape index), ``hypernet.onnx`` (the graph, reading its weights from that file;
see ``model.bundle.onnx_export``), ``instances.json`` (id, caption, shape id and shape index of
each training instance; with a query network also its palette shares in renders of its own codes,
``model.prior.colour_measure``), the optional components, and ``manifest.json`` last, listing the sha256
and size of every other file, the configs, the training data's attribution and the components.

Optional components: the query network (``query.safetensors`` and ``query.json`` as its run wrote
them, so ``model.prior.query.load_query`` reads the bundle folder too; ``query.onnx`` reading
``query.safetensors``; ``embeddings.npy``, the retrieval bank, one image embedding per instance in
``instances.json`` order) and the denoiser (``denoiser.safetensors`` + ``denoiser.json``, copied).

The bundle is written into a staging folder beside ``out`` and moved into place when complete, so
an interrupted export never leaves a half-written bundle under the final name.
"""

from __future__ import annotations

import json
import logging
import shutil
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from safetensors.torch import load_file

from model.bundle.attribution import training_attribution
from model.bundle.manifest import (
    BUNDLE_FORMAT,
    DENOISER_META,
    DENOISER_WEIGHTS,
    EMBEDDINGS,
    HYPERNET_ONNX,
    INSTANCES,
    MANIFEST,
    QUERY_ONNX,
    WEIGHTS,
    file_record,
)
from model.bundle.onnx_export import (
    export_hypernet_onnx,
    export_query_onnx,
    safetensors_spans,
)
from model.nerf import config
from model.nerf.provenance import source_digest
from model.prior.colour_measure import rendered_colours
from model.prior.io import PRIOR_WEIGHTS, Prior, load_prior
from model.prior.query import QUERY_META, QUERY_WEIGHTS, load_query

log = logging.getLogger(__name__)

QUERY_BANK = "bank.safetensors"
"""The retrieval bank a query-network run holds (``{"image": [I, E]}``, written by ``hypnerf train-query``)."""


def _check_target(out: Path) -> None:
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / MANIFEST).is_file())):
        raise ValueError(f"{out} exists and is not a bundle; choose another --out or remove it first")


def _dataset_folder(meta: dict, data: Path | None) -> Path:
    folder = Path(data) if data is not None else Path(meta["data"]) if meta.get("data") else None
    if folder is None or not (folder / "index.json").is_file():
        raise FileNotFoundError(
            f"the training data's index.json is not at {folder} (it gives the attribution); pass --data with the dataset the prior was trained on"
        )
    return folder


def _copy_denoiser(denoiser: Path, staging: Path) -> None:
    for name in (DENOISER_WEIGHTS, DENOISER_META):
        if not (denoiser / name).is_file():
            raise FileNotFoundError(f"{denoiser} lacks {name}; pass --denoiser a folder written by `hypnerf train-denoiser`")
    try:
        safetensors_spans(denoiser / DENOISER_WEIGHTS)
        json.loads((denoiser / DENOISER_META).read_text())
    except (ValueError, KeyError, UnicodeDecodeError) as error:
        raise ValueError(f"{denoiser}: the denoiser files are unreadable ({error}); train the denoiser again") from error
    for name in (DENOISER_WEIGHTS, DENOISER_META):
        shutil.copyfile(denoiser / name, staging / name)


def _export_query(query: Path, prior: Prior, staging: Path) -> dict:
    """Write the query component into ``staging``; returns its manifest config."""
    net = load_query(query)
    ids = [inst["id"] for inst in prior.instances]
    if net.meta.get("instances") != ids or (net.shape_dim, net.color_dim) != (prior.net.cfg.shape_code_dim, prior.net.cfg.color_code_dim):
        raise ValueError(f"the query network in {query} was not trained on this prior's instances and codes; train it on this run with `hypnerf train-query`")
    if not (query / QUERY_BANK).is_file():
        raise FileNotFoundError(f"{query} lacks its retrieval bank {QUERY_BANK}; train the query network again with `hypnerf train-query`")
    bank = load_file(str(query / QUERY_BANK))["image"].float().numpy()
    image = net.slot("image")
    if bank.shape != (len(ids), image.dim):
        raise ValueError(f"{query / QUERY_BANK} holds {list(bank.shape)} embeddings, expected [{len(ids)}, {image.dim}] ({image.name}); train the query network again")
    for name in (QUERY_WEIGHTS, QUERY_META):
        shutil.copyfile(query / name, staging / name)
    log.info("exporting the query network to ONNX (%s)", QUERY_ONNX)
    export_query_onnx(net, staging / QUERY_WEIGHTS, load_file(str(staging / QUERY_WEIGHTS)), staging / QUERY_ONNX)
    np.save(staging / EMBEDDINGS, np.ascontiguousarray(bank, dtype=np.float32))
    return {
        "inputs": [slot.to_json() for slot in net.slots],
        "retrieval": {"file": EMBEDDINGS, "modality": "image", "embedder": image.name, "instances": ids},
    }


def _configs(prior: Prior) -> dict:
    return {
        "hypernet": config.to_dict(prior.net.cfg),
        "field": config.to_dict(prior.net.cfg.field),
        "scene_box": prior.scene.to_aabb(),
        "camera": prior.meta["camera"],
        "weights_dtype": prior.meta.get("weights_dtype"),
    }


def _move_into_place(staging: Path, out: Path) -> None:
    if out.exists():
        previous = out.parent / f".{out.name}.previous"
        shutil.rmtree(previous, ignore_errors=True)
        out.rename(previous)
        staging.rename(out)
        shutil.rmtree(previous)
    else:
        staging.rename(out)


def _write(staging: Path, run: Path, prior: Prior, data: Path, query: Path | None, denoiser: Path | None) -> None:
    ids = [inst["id"] for inst in prior.instances]
    attribution = training_attribution(data, ids)
    log.info("writing %s (%d instances) from %s", WEIGHTS, len(ids), run / PRIOR_WEIGHTS)
    shutil.copyfile(run / PRIOR_WEIGHTS, staging / WEIGHTS)
    log.info("exporting the hypernetwork to ONNX (%s)", HYPERNET_ONNX)
    export_hypernet_onnx(prior.net, staging / WEIGHTS, load_file(str(staging / WEIGHTS)), staging / HYPERNET_ONNX)
    instances = prior.instances
    if query is not None:
        log.info("measuring each instance's colours in renders of its own codes (the query network's colour wearers)")
        instances = [{**inst, "rendered_colours": shares} for inst, shares in zip(instances, rendered_colours(prior), strict=True)]
    (staging / INSTANCES).write_text(json.dumps(instances, indent=1, ensure_ascii=False))
    configs, components = _configs(prior), ["hypernet"]
    if query is not None:
        configs["query"] = _export_query(query, prior, staging)
        components.append("query")
    if denoiser is not None:
        _copy_denoiser(denoiser, staging)
        components.append("denoiser")
    log.info("hashing the bundle's files")
    for path in staging.iterdir():
        path.chmod(0o644)  # readable by the service's own user (safetensors writes 0600)
    manifest = {
        "format": BUNDLE_FORMAT,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "generator": {"package": "hypnerf", "model_source": source_digest("nerf", "prior")},
        "components": components,
        "files": {p.name: file_record(p) for p in sorted(staging.iterdir())},
        "configs": configs,
        "training": {"run": run.name, "data": data.name, "summary": prior.meta.get("summary"), "train": prior.meta.get("train")},
        "attribution": attribution,
    }
    (staging / MANIFEST).write_text(json.dumps(manifest, indent=1, ensure_ascii=False))


def export_bundle(run: Path, out: Path, *, data: Path | None = None, query: Path | None = None, denoiser: Path | None = None) -> Path:
    """Write the bundle of the prior in ``run`` to ``out`` (replacing an earlier bundle there); returns ``out``.

    ``data``: the dataset folder whose ``index.json`` gives the attribution (default: the one the
    prior records); ``query``: a query-network run folder (``hypnerf train-query``); ``denoiser``: a
    folder with ``denoiser.safetensors`` and ``denoiser.json``.
    """
    run, out = Path(run), Path(out)
    _check_target(out)
    prior = load_prior(run)
    if "camera" not in prior.meta:
        raise ValueError(f"{run}/prior.json lacks the category's 'camera'; train the prior again with this version")
    folder = _dataset_folder(prior.meta, data)
    staging = out.parent / f".{out.name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        _write(staging, run, prior, folder, Path(query) if query is not None else None, Path(denoiser) if denoiser is not None else None)
        _move_into_place(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    log.info("bundle written to %s", out)
    return out
