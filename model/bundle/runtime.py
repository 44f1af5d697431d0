"""ONNX Runtime sessions of a bundle's graphs (the hypernetwork and the query network).

Each session runs on CUDA when this onnxruntime build has the CUDA provider, else on the CPU;
``threads`` bounds its intra-op thread pool (ONNX Runtime's own default: one per physical core).
A graph that cannot be loaded is a :class:`BundleError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import onnxruntime as ort

from model.bundle.manifest import BundleError


def onnx_session(path: Path, threads: int | None = None) -> ort.InferenceSession:
    """An inference session of the ONNX file at ``path`` (its external weights beside it)."""
    options = ort.SessionOptions()
    if threads is not None:
        if threads < 1:
            raise ValueError(f"intra-op threads must be at least 1, got {threads}")
        options.intra_op_num_threads = threads
    available = ort.get_available_providers()
    providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]
    try:
        return ort.InferenceSession(str(path), options, providers=providers)
    except Exception as error:  # onnxruntime's Fail, InvalidGraph, InvalidProtobuf... derive from Exception only
        raise BundleError(f"{path} could not be loaded by ONNX Runtime ({error}); re-export the bundle with `hypnerf export`") from error
