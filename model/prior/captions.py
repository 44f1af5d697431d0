"""Captions and paraphrases of an instance from its attributes, and held-out prompts.

An instance's attributes are read from its dataset entry: its main colour (the first palette
colour its caption names: captions are built from the mesh's dominant colour, see
``model.data.colours``), its noun (the catalogue name, e.g. "winchester armchair", else the
category) and its coarse type (armchair, stool, lounge chair, folding chair, high chair, chair),
which the evaluation scores text-to-NeRF against.

Training text is the dataset caption plus paraphrases from :data:`TRAIN_TEMPLATES` with the noun,
the type and the type's training paraphrases (:data:`TRAIN_TYPE_WORDS`), and with the colour's
training words (:data:`TRAIN_COLOUR_WORDS`). Composed captions (:func:`composed_captions`) name a
shape with a colour it was never rendered in; the query network learns them as that shape's code
with another instance's colour code (the prior's codes are disentangled: a colour code carries
its colours onto any shape), so "a purple lounge chair" has an answer although no training
instance is one. Held-out prompts use other templates (:data:`HELD_OUT_TEMPLATES`), so an
evaluation prompt is never a training sentence, other type words (:data:`TYPE_WORDS`), and
optionally colour words never seen in training (:data:`COLOUR_SYNONYMS`).
"""

from __future__ import annotations

import difflib
import functools
import random
import re
from dataclasses import dataclass

import numpy as np
from matplotlib.colors import XKCD_COLORS, to_rgb
from skimage.color import rgb2lab

from model.data.colours import PALETTE, article

# (keyword in the noun, type), first match wins
TYPE_RULES = (
    ("stool", "stool"),
    ("armchair", "armchair"),
    ("high chair", "high chair"),
    ("folding", "folding chair"),
    ("deck", "lounge chair"),
    ("beach", "lounge chair"),
    ("relax", "lounge chair"),
)
DEFAULT_TYPE = "chair"

TRAIN_TEMPLATES = (
    "{a} {colour} {noun}",
    "{colour} {noun}",
    "{a_noun} {noun} in {colour}",
    "{a} {colour} coloured {noun}",
    "the {noun} is {colour}",
    "{a_noun} {noun}",
    "{a_noun} {noun}, {colour}",
)
HELD_OUT_TEMPLATES = (
    "a photo of {a} {colour} {noun}",
    "I would like {a_noun} {noun} painted {colour}",
    "show me a {colour} {noun} for my living room",
    "a 3d model of {a} {colour} {noun}",
    "render {a} {colour} {noun}",
)
# colour words that no training caption uses (none contains a palette name), for held-out prompts
COLOUR_SYNONYMS = {
    "red": ("crimson", "scarlet"),
    "orange": ("tangerine", "amber"),
    "yellow": ("mustard", "lemon"),
    "green": ("emerald", "jade"),
    "teal": ("turquoise", "petrol"),
    "blue": ("navy", "cobalt"),
    "purple": ("violet", "plum"),
    "pink": ("rose", "blush"),
    "brown": ("chocolate", "walnut"),
    "beige": ("cream", "sand"),
    "black": ("jet", "ebony"),
    "white": ("ivory", "snow"),
    "grey": ("gray", "ash"),
}
# further colour words for training captions, disjoint from the held-out synonyms above
TRAIN_COLOUR_WORDS = {
    "red": ("ruby", "cherry"),
    "orange": ("apricot", "pumpkin"),
    "yellow": ("golden", "canary"),
    "green": ("olive", "lime"),
    "teal": ("aqua", "cyan"),
    "blue": ("azure", "sapphire"),
    "purple": ("lavender", "lilac"),
    "pink": ("salmon", "fuchsia"),
    "brown": ("coffee", "chestnut"),
    "beige": ("tan", "khaki"),
    "black": ("charcoal", "onyx"),
    "white": ("pearl", "milky"),
    "grey": ("silver", "slate"),
}
# type paraphrases for training captions, disjoint from the held-out type words below
TRAIN_TYPE_WORDS = {
    "armchair": ("chair with arms", "easy chair"),
    "stool": ("bar stool", "tall stool"),
    "lounge chair": ("reclining chair", "sun lounger"),
    "folding chair": ("foldable chair", "camping chair"),
    "high chair": ("baby chair", "feeding chair"),
    "chair": ("side chair", "kitchen chair"),
}
# type words for held-out prompts, one per type (the training nouns are catalogue names)
TYPE_WORDS = {
    "armchair": ("armchair", "arm chair"),
    "stool": ("stool", "backless stool"),
    "lounge chair": ("lounge chair", "deck chair"),
    "folding chair": ("folding chair",),
    "high chair": ("high chair",),
    "chair": ("chair", "dining chair"),
}


# a survey name whose palette word disagrees with its measured colour ("cloudy blue" is nearest
# white) is dropped, and one without a palette word is kept only when its nearest palette colour is
# clearly nearer than the second (distance ratio below this)
VOCABULARY_MARGIN = 0.75
# survey names are crowd-sourced; these keep the training text presentable
_CRUDE = ("shit", "poo", "puke", "vomit", "booger", "barf", "snot", "pee", "ugly", "nasty", "sick", "baby")


def _near_held_out(word: str, held_out: set[str]) -> bool:
    tokens = [t for t in re.findall(r"[a-z]+", word) if t not in PALETTE]  # "grey" is trained on, "gray" held out
    return any(h in word or difflib.SequenceMatcher(None, t, h).ratio() >= 0.75 for h in held_out for t in tokens)


@functools.cache
def colour_vocabulary() -> dict[str, tuple[str, ...]]:
    """Per palette colour, the XKCD survey's colour names filed under it (nearest in CIELAB, see
    :data:`VOCABULARY_MARGIN`), without any name that contains or nearly spells a held-out
    synonym (:data:`COLOUR_SYNONYMS`): no evaluation colour word is ever trained on."""
    from model.data.colours import colour_names

    held_out = {w for words in COLOUR_SYNONYMS.values() for w in words}
    names = [key.removeprefix("xkcd:") for key in XKCD_COLORS]
    rgb = np.array([to_rgb(value) for value in XKCD_COLORS.values()])
    palette = list(PALETTE)
    lab = rgb2lab(rgb[None])[0]
    palette_lab = rgb2lab(np.array([PALETTE[p] for p in palette])[None])[0]
    distance = np.sort(np.linalg.norm(lab[:, None] - palette_lab[None], axis=-1), axis=1)
    vocabulary: dict[str, list[str]] = {p: [] for p in palette}
    for name, nearest, (first, second) in zip(names, colour_names(rgb), distance[:, :2]):
        if _near_held_out(name, held_out) or any(c in name for c in _CRUDE):
            continue
        named = next((w for w in reversed(re.findall(r"[a-z]+", name)) if w in PALETTE), None)
        if named is not None and named != nearest or named is None and first > VOCABULARY_MARGIN * second:
            continue
        vocabulary[nearest].append(name)
    return {p: tuple(sorted(words)) for p, words in vocabulary.items()}


@dataclass(frozen=True)
class Attributes:
    """What captions say about an instance: main colour (a palette name or None), noun and type."""

    colour: str | None
    noun: str
    kind: str


def object_type(noun: str) -> str:
    """The coarse type of a catalogue noun (``"Bar stool"`` -> ``"stool"``)."""
    lowered = noun.lower()
    return next((kind for word, kind in TYPE_RULES if word in lowered), DEFAULT_TYPE)


def caption_colour(caption: str) -> str | None:
    """The first palette colour a caption names, if any."""
    for word in re.findall(r"[a-z]+", caption.lower()):
        if word in PALETTE:
            return word
    return None


def attributes(entry: dict) -> Attributes:
    """Attributes from an index entry (``caption``, ``category``, optional ``name``; for
    procedural chairs the ``attributes`` record says whether it has arms)."""
    noun = str(entry.get("name") or entry.get("category") or "object").lower()
    kind = object_type(noun)
    spec = entry.get("attributes")
    if isinstance(spec, dict) and spec.get("arms") and kind == DEFAULT_TYPE:
        kind = "armchair"
    return Attributes(caption_colour(str(entry.get("caption", ""))), noun, kind)


def _captions(colour: str | None, nouns: list[str]) -> list[str]:
    words = [colour, *TRAIN_COLOUR_WORDS.get(colour, ())] if colour else [None]
    texts = []
    for noun in nouns:
        for template in TRAIN_TEMPLATES:
            coloured = "{colour}" in template
            if colour is None and coloured:
                continue
            for word in words if coloured else words[:1]:
                texts.append(template.format(a=article(word or ""), colour=word, noun=noun, a_noun=article(noun)))
    return texts


def training_captions(caption: str, attrs: Attributes) -> list[str]:
    """The dataset caption and its paraphrases with the noun, the coarse type and its training
    paraphrases, each coloured with the palette name and its training colour words."""
    nouns = list(dict.fromkeys((attrs.noun, attrs.kind, *TRAIN_TYPE_WORDS.get(attrs.kind, ()))))
    return list(dict.fromkeys([caption, *_captions(attrs.colour, nouns)]))


def composed_captions(attrs: Attributes, colour: str) -> list[str]:
    """Captions of the shape ``attrs`` describes in another palette ``colour`` (type words only:
    the catalogue noun may itself name a colour or material)."""
    if colour not in PALETTE:
        raise ValueError(f"{colour!r} is not a palette colour")
    return list(dict.fromkeys(_captions(colour, list(dict.fromkeys((attrs.kind, *TRAIN_TYPE_WORDS.get(attrs.kind, ())))))))


def vocabulary_captions(nouns: list[str], colour: str, count: int, rng: random.Random) -> list[str]:
    """``count`` captions of one of ``nouns`` in palette ``colour``, each with a random training
    template and a random word of the colour's vocabulary (:func:`colour_vocabulary`)."""
    words = colour_vocabulary()[colour]
    templates = [t for t in TRAIN_TEMPLATES if "{colour}" in t]
    out = []
    for _ in range(count if words else 0):
        word, noun = rng.choice(words), rng.choice(nouns)
        out.append(rng.choice(templates).format(a=article(word), colour=word, noun=noun, a_noun=article(noun)))
    return out


def held_out_prompt(colour: str, kind: str, rng: random.Random, synonym: bool = False) -> str:
    """A prompt for ``colour`` and ``kind`` with a held-out template, and with ``synonym`` a colour
    word no training caption uses."""
    colour_word = rng.choice(COLOUR_SYNONYMS[colour]) if synonym else colour
    noun = rng.choice(TYPE_WORDS.get(kind, (kind,)))
    return rng.choice(HELD_OUT_TEMPLATES).format(a=article(colour_word), colour=colour_word, noun=noun, a_noun=article(noun))
