"""Verified loading of a bundle: every file's size and sha256 checked against the manifest, then
the hypernetwork's ONNX Runtime session (inference), its codebooks as arrays, the optional query
network and denoiser, and on demand the torch hypernetwork (test-time optimisation and
finetuning need gradients).

ONNX Runtime runs the hypernetwork once per NeRF (``Bundle.generate``); the session reads its
weights from ``weights.safetensors`` (``model.bundle.onnx_export``). The codebooks are read from
the same file with ``safetensors.safe_open``, which reads only the tensors asked for.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from model.bundle.manifest import (
    COLOR_INPUT,
    DENOISER_WEIGHTS,
    HYPERNET_ONNX,
    INSTANCES,
    SHAPE_INPUT,
    WEIGHTS,
    BundleError,
    read_manifest,
    verify_files,
)
from model.bundle.query import QueryModel
from model.bundle.runtime import onnx_session
from model.nerf import config
from model.nerf.fields import Field, FieldParams
from model.nerf.rays import Intrinsics
from model.nerf.scene import SceneBox
from model.prior.hypernet import HyperNetConfig, HyperNetwork
from model.prior.query import instance_colours


class Bundle:
    """A loaded, verified bundle (build it with :func:`load_bundle`).

    ``instances[i]`` is ``{"id", "caption", "shape_id", "shape_index", "attribution"}``;
    ``shape_codes [I, S]`` and ``color_codes [I, C]`` (float32) are the codes of instance ``i``
    (colour variants of one mesh share a shape code). ``query`` is the query network
    (:class:`model.bundle.query.QueryModel`) or ``None``; ``denoiser_path`` is the bundle's
    ``denoiser.safetensors`` (its ``denoiser.json`` beside it) or ``None``.
    """

    def __init__(self, path: Path, manifest: dict, digest: str, *, threads: int | None = None):
        self.path = Path(path)
        self.manifest = manifest
        self.digest = digest
        configs = manifest.get("configs", {})
        try:
            self._hypernet_cfg = config.from_dict(HyperNetConfig, configs["hypernet"])
            self.field: Field = self._hypernet_cfg.field
            self.scene = SceneBox.from_aabb(configs["scene_box"])
            self.camera = config.from_dict(Intrinsics, configs["camera"])
        except (KeyError, TypeError, ValueError) as error:
            raise BundleError(f"{self.path / 'manifest.json'} has invalid configs ({error}); re-export the bundle with `hypnerf export`") from error
        self.instances = self._read_instances()
        self._shape_index, self.shape_codes, self.color_codes = self._read_codes()
        self._ids = {inst["id"]: i for i, inst in enumerate(self.instances)}
        self._session = onnx_session(self.path / HYPERNET_ONNX, threads)
        self._outputs = [o.name for o in self._session.get_outputs()]
        components = manifest.get("components", [])
        self.query = QueryModel(self.path, self.shape_codes, self.color_codes, threads=threads,
                                instance_colours=instance_colours(self.instances),
                                rendered_colours=_rendered_colours(self.instances)) if "query" in components else None
        self.denoiser_path: Path | None = self.path / DENOISER_WEIGHTS if "denoiser" in components else None
        self._net: HyperNetwork | None = None
        self._net_lock = threading.Lock()

    def _read_instances(self) -> list[dict]:
        try:
            instances = json.loads((self.path / INSTANCES).read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise BundleError(f"{self.path / INSTANCES} is not valid JSON ({error}); re-export the bundle") from error
        attribution = {record["id"]: record for record in self.manifest.get("attribution", [])}
        return [{**inst, "attribution": attribution.get(inst["id"])} for inst in instances]

    def _read_codes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with safe_open(str(self.path / WEIGHTS), framework="pt") as weights:
            shape_index = weights.get_tensor("shape_index").long()
            shape_book = weights.get_tensor("shape_codes.weight").float()
            color_book = weights.get_tensor("color_codes.weight").float()
        if shape_index.tolist() != [inst["shape_index"] for inst in self.instances] or color_book.shape[0] != len(self.instances):
            raise BundleError(f"{self.path / INSTANCES} does not match the codebooks in {self.path / WEIGHTS}; re-export the bundle")
        return shape_index, shape_book[shape_index].numpy(), color_book.numpy()

    def instance_index(self, instance_id: str) -> int:
        """The row of ``instance_id`` in ``instances`` and the code arrays."""
        if instance_id not in self._ids:
            raise ValueError(f"{instance_id!r} is not an instance of this bundle; list them with GET /v1/instances or read {INSTANCES}")
        return self._ids[instance_id]

    @staticmethod
    def _code(values, size: int, what: str) -> np.ndarray:
        code = np.asarray(values, dtype=np.float32)
        if code.size != size or code.ndim > 2 or (code.ndim == 2 and code.shape[0] != 1):
            raise ValueError(f"a {what} code has {size} numbers (shape [{size}] or [1, {size}]); got shape {list(code.shape)}")
        if not np.isfinite(code).all():
            raise ValueError(f"the {what} code has NaN or infinite entries; every entry must be a finite number")
        return np.ascontiguousarray(code.reshape(1, size))

    def generate(self, shape: np.ndarray, color: np.ndarray) -> FieldParams:
        """The NeRF of a shape code ``[S]`` and colour code ``[C]`` (ONNX Runtime): float32 tensors with batch 1."""
        inputs = {SHAPE_INPUT: self._code(shape, self.shape_codes.shape[1], "shape"), COLOR_INPUT: self._code(color, self.color_codes.shape[1], "colour")}
        outputs = self._session.run(self._outputs, inputs)
        return {name: torch.from_numpy(value) for name, value in zip(self._outputs, outputs)}

    def hypernet(self) -> HyperNetwork:
        """The torch hypernetwork (float32, eval, parameters frozen), built from ``weights.safetensors``
        on first use and shared afterwards."""
        with self._net_lock:
            if self._net is None:
                net = HyperNetwork(self._hypernet_cfg, len(self.instances), self._shape_index.tolist())
                state = {k: v.float() if v.is_floating_point() else v for k, v in load_file(str(self.path / WEIGHTS)).items()}
                net.load_state_dict(state)
                self._net = net.eval().requires_grad_(False)
            return self._net


def _rendered_colours(instances: list[dict]) -> list[dict[str, float]] | None:
    """Each instance's palette shares in renders of its own codes as the export measured them, or
    None for a bundle exported without them (its colour wearers are then read from captions alone)."""
    shares = [inst.get("rendered_colours") for inst in instances]
    if all(s is None for s in shares):
        return None
    if not all(isinstance(s, dict) and all(isinstance(k, str) and isinstance(v, int | float) for k, v in s.items()) for s in shares):
        raise BundleError(f"{INSTANCES} has instances without valid 'rendered_colours' (palette name -> share); re-export the bundle")
    return shares


def load_bundle(path: Path, *, verify: bool = True, threads: int | None = None) -> Bundle:
    """Load the bundle in ``path``, refusing a tampered, truncated or missing file or a newer format.

    ``verify=False`` checks sizes but skips the sha256 of each file; ``threads`` sets ONNX Runtime's
    intra-op threads (default: its own choice, one per physical core).
    """
    path = Path(path)
    manifest, digest = read_manifest(path)
    verify_files(path, manifest, hashes=verify)
    return Bundle(path, manifest, digest, threads=threads)
