"""Training the query network Delta on a trained prior (paper section 3.2).

Each training instance contributes image embeddings of its training renders (views spread over
the hemisphere; computed once and cached, ``model.prior.embedding_cache``) and text embeddings of
its caption and paraphrases (``model.prior.captions``), plus composed captions naming each shape in
colours none of its instances wears, whose target is that shape's code with the colour code of an
instance in that colour. Every step draws a batch mixing images and texts; an input is the joint
embedding with only its own modality's slot filled, and its target is a (shape, colour) pair of
instances (the same instance but for composed captions). With the regression head (the default)
the loss is the mean squared error to the codes in standardised units, the paper's L_Delta; with
the codebook head it is the cross-entropy of the shape logits against the target's shape and of
the colour logits against the colour instance; with the shape-codebook head, the shape's
cross-entropy plus the colour code's squared error. AdamW with a cosine learning-rate decay.

Held-out views (the dataset's test frames, never trained on) give the top-1 retrieval printed
at the end: the nearest codebook instance to the predicted codes.

The output folder holds the network (``model.prior.query``) and ``bank.safetensors``, one image
embedding per instance (its views' mean direction) for retrieval by embedding.
"""

from __future__ import annotations

import json
import logging
import math
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from tqdm import tqdm

from model.data.dataset import load_index
from model.nerf import config
from model.data.colours import PALETTE
from model.prior.captions import TRAIN_TYPE_WORDS, attributes, composed_captions, training_captions, vocabulary_captions
from model.prior.embedders import embed_texts, load_embedder
from model.prior.embedding_cache import view_embeddings
from model.prior.io import load_prior
from model.prior.query import QueryConfig, QueryNetwork, input_slots, instance_bank, nearest_instances, save_query

log = logging.getLogger(__name__)

BANK_FILE = "bank.safetensors"


@dataclass
class QueryTrainConfig:
    """What the query network is trained on and how."""

    query: QueryConfig = field(default_factory=QueryConfig)
    image_embedder: str = "efficientnet-lite0"
    text_embedder: str = "minilm"
    views_per_instance: int = 24
    validation_views: int = 2
    steps: int = 2000
    batch: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-4
    text_fraction: float = 0.3
    composed_per_pair: int = 8
    """Composed captions per (shape, colour it is never rendered in); 0 trains on own captions only."""
    vocabulary_captions: int = 16
    """Captions naming the colour by a word of its vocabulary, per instance and per composed pair."""
    seed: int = 0

    def __post_init__(self):
        for name in ("views_per_instance", "steps", "batch"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name.replace('_', '-')} must be at least 1, got {getattr(self, name)}")
        for name in ("composed_per_pair", "vocabulary_captions"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name.replace('_', '-')} must be 0 or more, got {getattr(self, name)}")
        if not 0.0 <= self.text_fraction <= 1.0:
            raise ValueError(f"text_fraction must be in [0, 1], got {self.text_fraction}")


def instance_entries(data: Path, instances: list[dict]) -> list[dict]:
    """The index entries (as JSON records) of a prior's instances, in codebook order."""
    index = {entry.id: entry.to_json() for entry in load_index(data)}
    missing = [inst["id"] for inst in instances if inst["id"] not in index]
    if missing:
        raise ValueError(f"{data} lacks {len(missing)} of the prior's instances (e.g. {missing[0]}); pass the dataset the prior was trained on")
    return [index[inst["id"]] for inst in instances]


def image_embeddings(embedder, data: Path, ids: list[str], split: str, count: int, progress: bool = True) -> torch.Tensor:
    """Cached view embeddings of every instance: ``[I, V, E]``."""
    rows = [view_embeddings(embedder, data / object_id, split, count) for object_id in tqdm(ids, desc=f"embedding {split} views", unit="object", disable=not progress)]
    if len({r.shape[0] for r in rows}) != 1:
        raise ValueError(f"objects of {data} have different numbers of {split} views; re-render them with the same --views")
    return torch.stack(rows)


def caption_targets(entries: list[dict], shape_of: list[int], composed_per_pair: int, seed: int = 0,
                    vocabulary: int = 0) -> tuple[list[str], list[tuple[int, int]]]:
    """Every training text and its target ``(shape instance, colour instance)``: each instance's
    own captions (itself twice) and ``vocabulary`` captions naming its colour by vocabulary words,
    then for each shape and each palette colour none of its instances wears ``composed_per_pair``
    composed captions and ``vocabulary`` vocabulary captions, aimed at the shape's first instance
    and an instance wearing that colour (all drawn with a seeded generator)."""
    rng = random.Random(seed)
    words = random.Random(f"{seed}-vocabulary")  # its own stream: the other captions do not change with ``vocabulary``
    texts, owners = [], []

    def add(new: list[str], owner: tuple[int, int]):
        texts.extend(new)
        owners.extend([owner] * len(new))

    for n, entry in enumerate(entries):
        attrs = attributes(entry)
        add(training_captions(str(entry.get("caption", "")), attrs), (n, n))
        if vocabulary and attrs.colour:
            add(vocabulary_captions(_type_nouns(attrs, attrs.noun), attrs.colour, vocabulary, words), (n, n))
    if composed_per_pair or vocabulary:
        colours = [attributes(entry).colour for entry in entries]
        wearers = {c: [n for n, colour in enumerate(colours) if colour == c] for c in PALETTE}
        first = {}
        for n, shape in enumerate(shape_of):
            first.setdefault(shape, n)
        for shape, n in first.items():
            own = {colours[m] for m, s in enumerate(shape_of) if s == shape}
            attrs = attributes(entries[n])
            for colour in PALETTE:
                if colour in own or not wearers[colour]:
                    continue
                donor = rng.choice(wearers[colour])
                captions = composed_captions(attrs, colour)
                add(rng.sample(captions, min(composed_per_pair, len(captions))), (n, donor))
                # type words only, as composed captions: the catalogue noun may name a colour
                add(vocabulary_captions(_type_nouns(attrs), colour, vocabulary, words), (n, donor))
    return texts, owners


def _type_nouns(attrs, *extra: str) -> list[str]:
    return list(dict.fromkeys((*extra, attrs.kind, *TRAIN_TYPE_WORDS.get(attrs.kind, ()))))


def caption_embeddings(embedder, entries: list[dict], shape_of: list[int], composed_per_pair: int = 0, seed: int = 0,
                       vocabulary: int = 0) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Embeddings ``[T, E]`` of every training text, its target instances ``[T, 2]`` (shape, colour), and the texts."""
    texts, owners = caption_targets(entries, shape_of, composed_per_pair, seed, vocabulary)
    return embed_texts(embedder, texts), torch.tensor(owners), texts


def train_query(run: Path, data: Path, out: Path, cfg: QueryTrainConfig, device=None, progress: bool = True) -> dict:
    """Train Delta on the prior in ``run`` with the dataset ``data``; writes ``out``; returns its summary."""
    start = time.perf_counter()
    device = torch.device(device or "cpu")
    run, data, out = Path(run), Path(data), Path(out)
    prior = load_prior(run)
    instances = prior.instances
    entries = instance_entries(data, instances)
    ids = [inst["id"] for inst in instances]
    with torch.no_grad():
        shape_book, color_book = prior.net.codes(torch.arange(len(instances)))
        shapes = prior.net.shape_codes.weight.detach().clone()
    shape_of = prior.net.shape_index.clone()
    image_embedder = load_embedder(cfg.image_embedder)
    text_embedder = load_embedder(cfg.text_embedder) if cfg.text_embedder else None
    embedders = [image_embedder] + ([text_embedder] if text_embedder is not None and text_embedder is not image_embedder else [])
    views = image_embeddings(image_embedder, data, ids, "train", cfg.views_per_instance, progress)
    texts = caption_embeddings(text_embedder, entries, shape_of.tolist(), cfg.composed_per_pair, cfg.seed, cfg.vocabulary_captions) if text_embedder is not None else None
    log.info("training the query network on %d instances: %d views each%s", len(ids), views.shape[1],
             f", {len(texts[2])} captions" if texts else "")

    generator = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    meta = {"prior": str(run), "data": str(data), "embedders": [e.name for e in embedders], "instances": ids}
    net = QueryNetwork(cfg.query, input_slots(embedders), shape_book.shape[1], color_book.shape[1], meta, (len(shapes), len(color_book))).to(device)
    net.set_code_statistics(shapes, color_book)
    targets = ((torch.cat([shape_book, color_book], dim=1) - net.code_mean.cpu()) / net.code_scale.cpu()).to(device)
    shape_of = shape_of.to(device)
    image_slot = net.slot("image")
    text_slot = net.slot("text") if texts is not None else None
    optimiser = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda s: 0.5 * (1.0 + math.cos(math.pi * min(s, cfg.steps) / cfg.steps)))
    n_instances, n_views = views.shape[:2]
    flat_views = views.reshape(-1, views.shape[-1]).to(device)
    text_count = round(cfg.batch * cfg.text_fraction) if texts is not None else 0
    history = []
    net.train()
    bar = tqdm(range(cfg.steps), desc="query network", unit="step", disable=not progress)
    for step in bar:
        picks = torch.randint(0, n_instances * n_views, (cfg.batch - text_count,), generator=generator)
        inputs = torch.zeros(cfg.batch, net.input_dim, device=device)
        inputs[: len(picks), image_slot.offset : image_slot.offset + image_slot.dim] = flat_views[picks.to(device)]
        owners = (picks // n_views)[:, None].expand(-1, 2)
        if text_count:
            chosen = torch.randint(0, len(texts[1]), (text_count,), generator=generator)
            inputs[len(picks) :, text_slot.offset : text_slot.offset + text_slot.dim] = texts[0][chosen].to(device)
            owners = torch.cat([owners, texts[1][chosen]])
        shape_owner, color_owner = owners.to(device).unbind(1)
        output = net.outputs(inputs)
        if cfg.query.head == "codebook":
            loss = F.cross_entropy(output[:, : len(shapes)], shape_of[shape_owner]) + F.cross_entropy(output[:, len(shapes) :], color_owner)
        elif cfg.query.head == "shape-codebook":
            loss = F.cross_entropy(output[:, : len(shapes)], shape_of[shape_owner]) + F.mse_loss(
                output[:, len(shapes) :], targets[color_owner, shape_book.shape[1] :])
        else:
            split = shape_book.shape[1]
            target = torch.cat([targets[shape_owner, :split], targets[color_owner, split:]], dim=1)
            loss = F.mse_loss(output, target)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        schedule.step()
        if step % 100 == 0 or step == cfg.steps - 1:
            value = float(loss.detach())
            history.append({"step": step, "loss": value, "elapsed_s": time.perf_counter() - start})
            bar.set_postfix(loss=f"{value:.4f}")
    net.eval()

    validation = validate(net, image_embedder, data, ids, shape_book, color_book, cfg.validation_views, progress) if cfg.validation_views else None
    summary = {
        "instances": len(ids),
        "views_per_instance": n_views,
        "captions": len(texts[2]) if texts else 0,
        "composed_captions": int((texts[1][:, 0] != texts[1][:, 1]).sum()) if texts else 0,
        "steps": cfg.steps,
        "final_loss": history[-1]["loss"],
        "wall_s": time.perf_counter() - start,
        "validation": validation,
    }
    save_query(out, net.cpu(), {"train": config.to_dict(cfg), "summary": summary})
    save_file({"image": instance_bank(views).contiguous()}, str(out / BANK_FILE))
    (out / "history.json").write_text(json.dumps(history, indent=2))
    if validation:
        log.info("held-out views of training instances: top-1 %.1f%% (%d views)", 100 * validation["top1"], validation["queries"])
    return summary


@torch.no_grad()
def validate(net: QueryNetwork, embedder, data: Path, ids: list[str], shape_book: torch.Tensor, color_book: torch.Tensor, count: int, progress: bool) -> dict:
    """Top-1 retrieval of the instance from its dataset test frames (not trained on)."""
    held_out = image_embeddings(embedder, data, ids, "test", count, progress)
    truth = torch.arange(len(ids)).repeat_interleave(held_out.shape[1])
    shape, color = net(net.joint(image=held_out.reshape(-1, held_out.shape[-1])))
    found = nearest_instances(net, shape, color, shape_book, color_book, k=1)[:, 0]
    return {"queries": len(truth), "top1": float((found == truth).float().mean())}
