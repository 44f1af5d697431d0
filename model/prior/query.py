"""The query network Delta: an embedding -> a prior's (shape code, colour code) (paper section 3.2).

Delta is an MLP trained on embeddings of an instance's views and of its captions
(``model.train.query``) to give that instance's codes: by regression onto the codebook (the
paper's loss, the default) or as a choice among codebook entries trained as a classification of
the instance (see :class:`QueryConfig`; measured against each other in BENCHMARKS.md). Its input is one *joint* embedding ``[B, E]``: the
concatenation of one slot per embedder named in ``meta["inputs"]`` (text slot, image slot; CLIP's
one shared space is a single slot for both). A query fills the slots it has and leaves the others
zero, so one network (and one ONNX graph) answers text, images, or both together. Outputs are
at the codebook's scale; the codebook's per-dimension mean and spread (buffers of the module) are
the units of code distances (:func:`code_distances`, snapping).

Weights are safetensors (``query.safetensors``) beside ``query.json`` (config, inputs, provenance);
never pickle.

Retrieval is a pure function on embeddings: :func:`retrieve` ranks a bank of per-instance
embeddings by cosine similarity. The bank a query run writes (``bank.safetensors``) holds one image
embedding per instance, the mean direction of its training views' embeddings (:func:`instance_bank`).
Measured on new views (``hypnerf eval retrieval``, BENCHMARKS.md), Delta's codes matched to the
nearest codebook instance retrieve best, every view of every instance with the best view per
instance next, and the per-instance mean last: the bank is the compact fallback, not the best way.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from model.data.colours import largest_share
from model.nerf import config
from model.prior.captions import caption_colour
from model.prior.colour_words import PromptColour, palette_prompt
from model.prior.embedders import Embedder

QUERY_WEIGHTS = "query.safetensors"
QUERY_META = "query.json"
QUERY_FORMAT = 1


HEADS = ("codebook", "regression", "shape-codebook")


@dataclass
class QueryConfig:
    """Sizes of the MLP (``layers`` hidden layers of ``hidden`` units: LayerNorm, GELU, dropout)
    and its head:

    - ``codebook``: logits over the codebook's shape codes and colour codes, trained as a
      classification of the instance; the codes are the most likely shape code and the most likely
      colour code, so an ambiguous prompt picks one fitting codebook entry instead of decoding
      the mean of all that fit (a faded blend);
    - ``regression`` (default): the codes themselves, in codebook-standardised units (the paper's
      L_Delta); callers snap them to the codebook (:func:`snap_codes`) to avoid blends;
    - ``shape-codebook``: logits over the shape codes (a classification of the shape: a prompt's
      type picks one fitting shape instead of landing between shapes) and the colour code by
      regression (colours a prompt names are compositions the colour codebook may lack).
    """

    hidden: int = 512
    layers: int = 2
    dropout: float = 0.1
    head: str = "regression"

    def __post_init__(self):
        if self.head not in HEADS:
            raise ValueError(f"unknown query head {self.head!r}; choose one of {HEADS}")


@dataclass(frozen=True)
class InputSlot:
    """One embedder's part of the joint embedding: columns ``[offset, offset + dim)``."""

    name: str
    modalities: tuple[str, ...]
    dim: int
    offset: int
    version: str = ""

    def to_json(self) -> dict:
        return {"name": self.name, "modalities": list(self.modalities), "dim": self.dim, "offset": self.offset, "version": self.version}

    @classmethod
    def from_json(cls, data: dict) -> InputSlot:
        return cls(str(data["name"]), tuple(data["modalities"]), int(data["dim"]), int(data["offset"]), str(data.get("version", "")))


def input_slots(embedders: list[Embedder]) -> list[InputSlot]:
    """Consecutive slots for embedders, in order."""
    slots, offset = [], 0
    for embedder in embedders:
        slots.append(InputSlot(embedder.name, tuple(embedder.modalities), int(embedder.dim), offset, embedder.version()))
        offset += int(embedder.dim)
    modalities = [m for slot in slots for m in slot.modalities]
    if len(modalities) != len(set(modalities)):
        raise ValueError(f"two embedders read the same modality ({modalities}); give one embedder per modality")
    return slots


def slot_modalities(slots: list[InputSlot]) -> tuple[str, ...]:
    """Every modality the slots of a joint embedding read, in slot order."""
    return tuple(m for slot in slots for m in slot.modalities)


def slot_for(slots: list[InputSlot], modality: str) -> InputSlot | None:
    """The slot that reads ``modality`` (``"text"``, ``"image"``), or None."""
    return next((slot for slot in slots if modality in slot.modalities), None)


class QueryNetwork(nn.Module):
    """``forward(embedding [B, E]) -> (shape [B, S], color [B, C])``; ``meta`` names the embedders.
    A codebook head holds the codebooks (``shape_book [N_s, S]``, one row per shape, and
    ``color_book [I, C]``) as buffers: ``codebook`` gives their sizes."""

    def __init__(self, cfg: QueryConfig, slots: list[InputSlot], shape_dim: int, color_dim: int, meta: dict | None = None,
                 codebook: tuple[int, int] = (0, 0)):
        super().__init__()
        if cfg.head != "regression" and min(codebook) < 1:
            raise ValueError("a codebook head needs the codebook sizes (shapes, colours)")
        if not slots:
            raise ValueError("a query network needs at least one embedder")
        self.cfg = cfg
        self.slots = list(slots)
        self.shape_dim, self.color_dim = int(shape_dim), int(color_dim)
        self.input_dim = sum(slot.dim for slot in slots)
        blocks: list[nn.Module] = []
        width = self.input_dim
        for _ in range(cfg.layers):
            blocks += [nn.Linear(width, cfg.hidden), nn.LayerNorm(cfg.hidden), nn.GELU(), nn.Dropout(cfg.dropout)]
            width = cfg.hidden
        self.codebook_sizes = tuple(int(n) for n in codebook) if cfg.head != "regression" else (0, 0)
        outputs = {"codebook": sum(self.codebook_sizes), "regression": self.shape_dim + self.color_dim,
                   "shape-codebook": self.codebook_sizes[0] + self.color_dim}[cfg.head]
        blocks.append(nn.Linear(width, outputs))
        self.mlp = nn.Sequential(*blocks)
        self.register_buffer("code_mean", torch.zeros(self.shape_dim + self.color_dim))
        self.register_buffer("code_scale", torch.ones(self.shape_dim + self.color_dim))
        if cfg.head != "regression":
            self.register_buffer("shape_book", torch.zeros(self.codebook_sizes[0], self.shape_dim))
        if cfg.head == "codebook":
            self.register_buffer("color_book", torch.zeros(self.codebook_sizes[1], self.color_dim))
        self.meta = dict(meta or {})

    @property
    def modalities(self) -> tuple[str, ...]:
        return slot_modalities(self.slots)

    def slot(self, modality: str) -> InputSlot:
        found = slot_for(self.slots, modality)
        if found is None:
            raise ValueError(f"this query network reads {self.modalities}, not {modality!r}; train one with an embedder for it")
        return found

    def joint(self, **parts: torch.Tensor) -> torch.Tensor:
        """The joint embedding ``[B, E]`` of per-modality embeddings, e.g. ``joint(text=t [B, 384])``;
        slots not given stay zero."""
        given = {m: e for m, e in parts.items() if e is not None}
        if not given:
            raise ValueError(f"give at least one embedding of {self.modalities}")
        batch = {e.shape[0] for e in given.values()}
        if len(batch) != 1:
            raise ValueError(f"embeddings of one query must have the same batch size, got {sorted(batch)}")
        out = torch.zeros(batch.pop(), self.input_dim, device=self.code_mean.device)
        for modality, embedding in given.items():
            slot = self.slot(modality)
            if embedding.ndim != 2 or embedding.shape[1] != slot.dim:
                raise ValueError(f"the {modality} embedding must be [B, {slot.dim}] ({slot.name}), got {tuple(embedding.shape)}")
            out[:, slot.offset : slot.offset + slot.dim] += embedding.to(out)
        return out

    def set_code_statistics(self, shape_codes: torch.Tensor, color_codes: torch.Tensor) -> None:
        """Standardise outputs (and code distances) by the codebooks' per-dimension mean and spread
        (``shape_codes [N_s, S]``: one row per shape; ``color_codes [I, C]``); a codebook head keeps the codebooks."""
        codes = torch.cat([shape_codes.mean(0), color_codes.mean(0)])
        scale = torch.cat([shape_codes.std(0, unbiased=False), color_codes.std(0, unbiased=False)])
        self.code_mean.copy_(codes)
        self.code_scale.copy_(scale.clamp_min(1e-6))
        if self.cfg.head != "regression":
            if (len(shape_codes), len(color_codes)) != self.codebook_sizes:
                raise ValueError(f"this codebook head has {self.codebook_sizes} entries, got {(len(shape_codes), len(color_codes))}")
            self.shape_book.copy_(shape_codes)
        if self.cfg.head == "codebook":
            self.color_book.copy_(color_codes)

    def outputs(self, embedding: torch.Tensor) -> torch.Tensor:
        """The head's raw output ``[B, K]``: standardised codes (regression), shape then colour logits
        (codebook), or shape logits then the standardised colour code (shape-codebook)."""
        if embedding.ndim != 2 or embedding.shape[1] != self.input_dim:
            raise ValueError(f"the query network takes joint embeddings [B, {self.input_dim}], got {tuple(embedding.shape)}")
        return self.mlp(embedding)

    def forward(self, embedding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.outputs(embedding)
        shapes = self.codebook_sizes[0]
        # F.embedding exports as a Gather on the stored codebook (indexing was exported with a derived copy of it)
        if self.cfg.head == "codebook":
            return F.embedding(out[:, :shapes].argmax(dim=1), self.shape_book), F.embedding(out[:, shapes:].argmax(dim=1), self.color_book)
        if self.cfg.head == "shape-codebook":
            # scale the whole code and slice the result: a slice of a buffer would be exported as a second copy of it
            codes = torch.cat([out.new_zeros(out.shape[0], self.shape_dim), out[:, shapes:]], dim=1) * self.code_scale + self.code_mean
            return F.embedding(out[:, :shapes].argmax(dim=1), self.shape_book), codes[:, self.shape_dim :]
        codes = out * self.code_scale + self.code_mean
        return codes[:, : self.shape_dim], codes[:, self.shape_dim :]


def save_query(path: Path, net: QueryNetwork, extra: dict | None = None) -> Path:
    """Write ``path/query.safetensors`` and ``path/query.json`` (config, inputs, meta, ``extra``)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().float().contiguous().cpu() for k, v in net.state_dict().items()}, str(path / QUERY_WEIGHTS))
    meta = {
        "format": QUERY_FORMAT,
        "config": config.to_dict(net.cfg),
        "inputs": [slot.to_json() for slot in net.slots],
        "shape_dim": net.shape_dim,
        "color_dim": net.color_dim,
        "codebook": list(net.codebook_sizes),
        **net.meta,
        **(extra or {}),
    }
    (path / QUERY_META).write_text(json.dumps(meta, indent=2))
    return path / QUERY_WEIGHTS


def load_query(path: Path, device=None) -> QueryNetwork:
    """A trained query network (float32, eval mode) from a folder written by :func:`save_query`."""
    path = Path(path)
    if not (path / QUERY_WEIGHTS).is_file() or not (path / QUERY_META).is_file():
        raise FileNotFoundError(f"{path} holds no query network ({QUERY_WEIGHTS} and {QUERY_META}); train one with `hypnerf train-query`")
    meta = json.loads((path / QUERY_META).read_text())
    if meta.get("format", 0) > QUERY_FORMAT:
        raise ValueError(f"{path / QUERY_META} has format {meta.get('format')}, newer than this code reads ({QUERY_FORMAT}); update hypnerf")
    slots = [InputSlot.from_json(s) for s in meta["inputs"]]
    known = {"format", "config", "inputs", "shape_dim", "color_dim", "codebook"}
    net = QueryNetwork(config.from_dict(QueryConfig, meta["config"]), slots, meta["shape_dim"], meta["color_dim"],
                       {k: v for k, v in meta.items() if k not in known}, tuple(meta.get("codebook", (0, 0))))
    net.load_state_dict(load_file(str(path / QUERY_WEIGHTS)))
    return net.to(device or "cpu").eval()


# ---------------------------------------------------------------------------------------------
# Codes and retrieval


def code_distances(net: QueryNetwork, shape: torch.Tensor, color: torch.Tensor, shape_book: torch.Tensor, color_book: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distances in standardised code units from predicted codes ``[B, S]``, ``[B, C]`` to
    each instance's codes ``[I, S]``, ``[I, C]``: ``(shape part [B, I], colour part [B, I])``."""
    s_scale, c_scale = net.code_scale[: net.shape_dim], net.code_scale[net.shape_dim :]
    shape_d = torch.cdist(shape / s_scale, shape_book.to(shape) / s_scale).pow(2) / net.shape_dim
    color_d = torch.cdist(color / c_scale, color_book.to(color) / c_scale).pow(2) / net.color_dim
    return shape_d, color_d


def nearest_instances(net: QueryNetwork, shape: torch.Tensor, color: torch.Tensor, shape_book: torch.Tensor, color_book: torch.Tensor, k: int = 1) -> torch.Tensor:
    """The ``k`` instances ``[B, k]`` whose (shape, colour) codes are nearest the predicted ones."""
    shape_d, color_d = code_distances(net, shape, color, shape_book, color_book)
    return (shape_d + color_d).topk(min(k, shape_d.shape[1]), dim=1, largest=False).indices


def snap_codes(net: QueryNetwork, shape: torch.Tensor, color: torch.Tensor, shape_book: torch.Tensor, color_book: torch.Tensor,
               colour_rows: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each predicted code replaced by its nearest codebook entry, shape and colour separately
    (the result may pair one instance's shape with another's colour). A regression from an
    ambiguous query lands between codes, and a point between codes decodes to a faded blend of
    chairs; a codebook entry decodes to a sharp one. ``colour_rows`` (``[I]`` bool), when it
    selects any, restricts the colour to those instances' codes (the wearers of a colour a
    prompt names)."""
    shape_d, color_d = code_distances(net, shape, color, shape_book, color_book)
    if colour_rows is not None and bool(colour_rows.any()):
        color_d = color_d.masked_fill(~colour_rows.to(color_d.device)[None], math.inf)
    return shape_book[shape_d.argmin(dim=1)].to(shape), color_book[color_d.argmin(dim=1)].to(color)


def instance_colours(instances: list[dict]) -> list[str | None]:
    """The palette colour each instance's caption names (None where it names none)."""
    return [caption_colour(str(inst.get("caption", ""))) for inst in instances]


def colour_wearers(colours: list[str | None], colour: str | None, shares: list[dict[str, float]] | None = None) -> list[int]:
    """The instances wearing palette ``colour``: those whose caption names it (``colours``, from
    :func:`instance_colours`), narrowed to those whose own renders it dominates when ``shares``
    (each instance's palette shares, ``model.prior.colour_measure.rendered_colours``) are given and
    any such instance exists. A caption names a chair's largest material, which need not be what
    its colour code paints most of another shape. Empty for no colour or no wearer."""
    if colour is None:
        return []
    captioned = [n for n, c in enumerate(colours) if c == colour]
    if shares is None:
        return captioned
    dominated = [n for n in captioned if shares[n] and largest_share(shares[n]) == colour]
    return dominated or captioned


def colour_rows(colours: list[str | None], colour: str | None, shares: list[dict[str, float]] | None = None) -> torch.Tensor | None:
    """``[I]`` bool: the instances wearing palette ``colour`` (:func:`colour_wearers`), None for no colour."""
    if colour is None:
        return None
    rows = torch.zeros(len(colours), dtype=torch.bool)
    rows[colour_wearers(colours, colour, shares)] = True
    return rows


def instance_bank(view_embeddings: torch.Tensor) -> torch.Tensor:
    """One embedding per instance ``[I, E]`` from its views' embeddings ``[I, V, E]``: the mean
    direction (mean of the L2-normalised embeddings, renormalised)."""
    if view_embeddings.ndim != 3:
        raise ValueError(f"view embeddings must be [instances, views, E], got {tuple(view_embeddings.shape)}")
    return F.normalize(F.normalize(view_embeddings, dim=-1).mean(dim=1), dim=-1)


def retrieve(embedding: torch.Tensor, bank: torch.Tensor, k: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` bank rows most similar to a query: ``embedding [E]``, ``bank [N, E]`` ->
    ``(indices [k], cosine similarities [k])``, best first. Pure: no model, no state."""
    if embedding.ndim != 1 or bank.ndim != 2 or bank.shape[1] != embedding.shape[0]:
        raise ValueError(f"retrieve takes an embedding [E] and a bank [N, E], got {tuple(embedding.shape)} and {tuple(bank.shape)}")
    if len(bank) == 0:
        raise ValueError("the retrieval bank is empty")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    scores = F.normalize(bank.float(), dim=-1) @ F.normalize(embedding.float(), dim=0)
    top = scores.topk(min(k, len(bank)))
    return top.indices, top.values


# ---------------------------------------------------------------------------------------------
# From a query to codes


class QueryPipeline:
    """A prior, its query network and the embedders it reads: prompts and images -> codes.

    ``codes(text=..., image=...)`` embeds what it is given, runs Delta and, with ``snap``, replaces
    each code by its nearest codebook entry (:func:`snap_codes`)."""

    def __init__(self, prior, net: QueryNetwork, device=None):
        from model.prior.embedders import load_embedder

        self.prior, self.net = prior, net
        self.device = torch.device(device or "cpu")
        self.embedders = {m: load_embedder(slot.name, self.device) for slot in net.slots for m in slot.modalities}
        with torch.no_grad():
            self.shape_book, self.color_book = prior.net.codes(torch.arange(len(prior.instances), device=prior.device))
        self.instance_colours = instance_colours(prior.instances)
        self._rendered_colours: list[dict[str, float]] | None = None

    @property
    def rendered_colours(self) -> list[dict[str, float]]:
        """Each instance's palette shares in renders of its own codes, measured on first use (cached on disk)."""
        if self._rendered_colours is None:
            from model.prior.colour_measure import rendered_colours

            self._rendered_colours = rendered_colours(self.prior)
        return self._rendered_colours

    @classmethod
    def from_runs(cls, run: Path, query: Path, device=None) -> QueryPipeline:
        from model.prior.io import load_prior

        return cls(load_prior(run, device), load_query(query, device), device)

    def embed(self, text: str | None = None, image: torch.Tensor | None = None) -> torch.Tensor:
        """The joint embedding ``[1, E]`` of a prompt as it is and/or an RGBA image ``[H, W, 4]``
        (see :meth:`text_embedding` for a prompt with its colour words read)."""
        from model.prior.embedders import embed_queries, embed_texts

        parts = {}
        if text is not None:
            parts["text"] = embed_texts(self._embedder("text"), [text])
        if image is not None:
            parts["image"] = embed_queries(self._embedder("image"), image[None] if image.ndim == 3 else image)
        return self.net.joint(**parts)

    def _embedder(self, modality: str):
        if modality not in self.embedders:
            raise ValueError(f"this query network reads {self.net.modalities}, not {modality}; train it with a {modality} embedder")
        return self.embedders[modality]

    @torch.no_grad()
    def codes(self, embedding: torch.Tensor, snap: bool = True, colour: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Codes ``([B, S], [B, C])`` of joint embeddings ``[B, E]``; with ``snap``, a palette
        ``colour`` restricts the colour code to the instances wearing it (:func:`colour_wearers`:
        captioned with it and, where any is, dominated by it in their own renders)."""
        shape, color = self.net(embedding.to(self.device))
        if snap:
            wearers = colour_rows(self.instance_colours, colour, self.rendered_colours) if colour is not None else None
            shape, color = snap_codes(self.net, shape, color, self.shape_book, self.color_book, wearers)
        return shape, color

    def text_embedding(self, prompt: str, read_colours: bool = True) -> tuple[torch.Tensor, PromptColour]:
        """The joint embedding ``[1, E]`` of a prompt and what was read from it: with
        ``read_colours`` its colour words read as palette colours (``model.prior.colour_words``);
        pass the read palette colour to :meth:`codes` to constrain the snapped colour code."""
        read = palette_prompt(prompt) if read_colours else PromptColour(prompt)
        return self.embed(text=read.prompt), read
