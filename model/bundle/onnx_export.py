"""The bundle's networks as ONNX graphs whose weights live in the bundle's safetensors files.

Two graphs: the hypernetwork (``hypernet.onnx``: inputs ``shape [B, S]`` and ``color [B, C]``
float32; outputs one float32 tensor per emitted NeRF parameter, named as in ``FieldParams``:
``tables [B, L, T, F]``, ``density0``, ...) and the query network (``query.onnx``: input
``embedding [B, E]``; outputs ``shape [B, S]`` and ``color [B, C]``).

Export uses ``torch.onnx.export(dynamo=True)`` (the ``torch.export`` based exporter, with
onnxscript's graph optimiser): on these networks it emits one ``Gemm`` per linear layer with every
weight as an untransformed initialiser named by its state-dict key. The legacy TorchScript
exporter was measured too: it folds the bias-free bottleneck's transpose into an anonymous second
copy of that weight, which the rule below would refuse.

Each weight is stored once. The graph's weight initialisers are ONNX *external data* whose
``location`` is the safetensors file beside the graph and whose ``offset``/``length`` are the
tensor's bytes in that file (safetensors: an 8-byte little-endian header length, a JSON header with
each tensor's byte range, then raw little-endian tensors), so the ``.onnx`` file holds only the
graph (tens of KB). Weights keep their stored precision (float16 for the shipped prior) and a
``Cast`` to float32 in front of the graph widens them; ONNX Runtime folds those casts into float32
constants when the session is created, so inference runs in float32 on exactly the values torch
loads (``load_prior`` promotes the same float16 tensors). Export refuses a graph holding any float
constant that is not a stored weight (a derived copy). The alternative, building the torch
networks from ONNX initialisers, would tie the training side to the ONNX format; the safetensors
files stay the one source that torch (``safetensors.torch``) and ONNX Runtime both read.
"""

from __future__ import annotations

import contextlib
import json
import logging
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, numpy_helper
from torch import nn

from model.bundle.manifest import COLOR_INPUT, EMBEDDING_INPUT, SHAPE_INPUT
from model.prior.hypernet import HyperNetwork
from model.prior.query import QueryNetwork

# safetensors dtype names -> ONNX element types (floating weights only: the graphs read no others)
_ONNX_TYPES = {"F16": TensorProto.FLOAT16, "BF16": TensorProto.BFLOAT16, "F32": TensorProto.FLOAT, "F64": TensorProto.DOUBLE}
_FLOAT_TYPES = (TensorProto.FLOAT, TensorProto.FLOAT16, TensorProto.BFLOAT16, TensorProto.DOUBLE)
# the wrappers below hold the network as ``net``, so its initialisers are named ``net.<state-dict key>``
_PREFIX = "net."


@dataclass(frozen=True)
class TensorSpan:
    """Where one tensor's raw bytes lie in a safetensors file."""

    dtype: str
    shape: tuple[int, ...]
    offset: int
    length: int


def safetensors_spans(path: Path) -> dict[str, TensorSpan]:
    """Byte ranges of every tensor in a safetensors file, by tensor name."""
    with open(path, "rb") as handle:
        (header_length,) = struct.unpack("<Q", handle.read(8))
        header = json.loads(handle.read(header_length))
    start = 8 + header_length
    spans = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        begin, end = info["data_offsets"]
        spans[name] = TensorSpan(info["dtype"], tuple(info["shape"]), start + begin, end - begin)
    return spans


class _Emitter(nn.Module):
    """``(shape [B, S], color [B, C]) -> one tensor per emitted parameter``, in emission order."""

    def __init__(self, net: HyperNetwork):
        super().__init__()
        self.net = net
        self.names = list(net.heads)

    def forward(self, shape: torch.Tensor, color: torch.Tensor) -> tuple[torch.Tensor, ...]:
        params = self.net.params_from_codes(shape, color)
        return tuple(params[name] for name in self.names)


class _QueryCodes(nn.Module):
    """``embedding [B, E] -> (shape [B, S], color [B, C])``."""

    def __init__(self, net: QueryNetwork):
        super().__init__()
        self.net = net

    def forward(self, embedding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net(embedding)


@contextlib.contextmanager
def _quiet_exporter():
    """Silence the exporter's per-pass INFO logs and its internal deprecation notices."""
    quiet = {"onnxscript": logging.WARNING, "onnx_ir": logging.WARNING,
             # it warns once per torchvision operator it cannot register; this project has no torchvision
             "torch.onnx._internal.exporter._registration": logging.ERROR}
    loggers = [logging.getLogger(name) for name in quiet]
    levels = [logger.level for logger in loggers]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)
        warnings.filterwarnings("ignore", message=".*axis name.*will not be used.*", category=UserWarning)
        for logger, level in zip(loggers, quiet.values()):
            logger.setLevel(level)
        try:
            yield
        finally:
            for logger, level in zip(loggers, levels):
                logger.setLevel(level)


def _trace(module: nn.Module, inputs: dict[str, torch.Tensor], outputs: list[str]) -> onnx.ModelProto:
    """The float32 graph of ``module`` with embedded weights, straight from the exporter; dimension 0 of every input is the batch."""
    batch = torch.export.Dim("batch")
    with _quiet_exporter():
        program = torch.onnx.export(
            module.eval(), tuple(inputs.values()), input_names=list(inputs), output_names=outputs,
            dynamic_shapes=tuple({0: batch} for _ in inputs), dynamo=True, optimize=True, verbose=False,
        )
    return program.model_proto


def _external(name: str, span: TensorSpan, location: str) -> TensorProto:
    tensor = TensorProto(name=name, data_type=_ONNX_TYPES[span.dtype], dims=list(span.shape), data_location=TensorProto.EXTERNAL)
    for key, value in (("location", location), ("offset", str(span.offset)), ("length", str(span.length))):
        entry = tensor.external_data.add()
        entry.key, entry.value = key, value
    return tensor


def _point_weights_at(model: onnx.ModelProto, weights: Path, stored: dict[str, torch.Tensor]) -> None:
    """Replace every weight initialiser by a reference into ``weights`` (cast to float32 when stored narrower)."""
    spans = safetensors_spans(weights)
    graph = model.graph
    kept, references, casts = [], [], []
    for init in graph.initializer:
        key = init.name.removeprefix(_PREFIX)
        if key not in spans:
            if init.data_type in _FLOAT_TYPES and int(np.prod(init.dims)) > 1:
                raise RuntimeError(f"the exported graph holds a float tensor that is not a stored weight ({init.name}, {list(init.dims)}): "
                                   "a derived copy would store that weight twice")
            kept.append(init)
            continue
        if not np.array_equal(numpy_helper.to_array(init), stored[key].float().numpy()):
            raise RuntimeError(f"the exported graph's {init.name} differs from the stored weight {key}")
        span = spans[key]
        if span.dtype == "F32":
            references.append(_external(init.name, span, weights.name))
        else:
            references.append(_external(f"{key}:stored", span, weights.name))
            casts.append(onnx.helper.make_node("Cast", [f"{key}:stored"], [init.name], to=TensorProto.FLOAT, name=f"widen/{key}"))
    nodes = casts + list(graph.node)
    del graph.initializer[:]
    graph.initializer.extend(kept + references)
    del graph.node[:]
    graph.node.extend(nodes)


def _export(module: nn.Module, inputs: dict[str, torch.Tensor], outputs: list[str], weights: Path, stored: dict[str, torch.Tensor], out: Path, doc: str) -> Path:
    if Path(weights).parent.resolve() != Path(out).parent.resolve():
        raise ValueError(f"{out} must sit beside {weights}: ONNX external data is found relative to the model file")
    model = _trace(module, inputs, outputs)
    _point_weights_at(model, Path(weights), stored)
    # the exporter annotates nodes with Python stack traces (absolute paths of this machine): not part of the model
    for node in model.graph.node:
        del node.metadata_props[:]
    model.doc_string = f"{doc}; weights in {Path(weights).name}"
    Path(out).write_bytes(model.SerializeToString())
    onnx.checker.check_model(str(out), full_check=True)
    return Path(out)


def export_hypernet_onnx(net: HyperNetwork, weights: Path, stored: dict[str, torch.Tensor], out: Path) -> Path:
    """Write ``out``: the hypernetwork's graph reading its weights from ``weights`` (a safetensors file
    in the same folder holding ``stored``, the state dict in its stored precision)."""
    inputs = {SHAPE_INPUT: torch.zeros(1, net.cfg.shape_code_dim), COLOR_INPUT: torch.zeros(1, net.cfg.color_code_dim)}
    return _export(_Emitter(net), inputs, list(net.heads), weights, stored, out, "hypnerf hypernetwork: (shape code, colour code) -> NeRF parameters")


def export_query_onnx(net: QueryNetwork, weights: Path, stored: dict[str, torch.Tensor], out: Path) -> Path:
    """Write ``out``: the query network's graph (joint embedding -> codes) reading its weights from ``weights``."""
    inputs = {EMBEDDING_INPUT: torch.zeros(1, net.input_dim)}
    return _export(_QueryCodes(net), inputs, [SHAPE_INPUT, COLOR_INPUT], weights, stored, out, "hypnerf query network: joint embedding -> (shape code, colour code)")
