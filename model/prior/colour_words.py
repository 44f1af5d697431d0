"""Colour words in a prompt, read with a colour lexicon and rewritten as the palette colour they name.

The text encoders that ship offline know little about colour names: with all-MiniLM-L6-v2 the
nearest of some 500 survey colour names to a held-out word such as "crimson" or "navy" names the
right palette colour for about a quarter of them, so a query network trained on palette words and a
few synonyms turns most unseen colour words into a guess. A lexicon knows them: the names of the
XKCD colour survey (about 950 crowd-sourced names, as people use them) and then the CSS4 names,
with their sRGB, both shipped by **matplotlib** (``matplotlib.colors``). A prompt that names no
palette colour but contains a lexicon name (the longest run of up to three words) is rewritten with
the palette colour nearest that name in CIELAB, the measure ``model.data.colours`` names colours by,
before it is embedded: "a photo of a crimson high chair" is read as "a photo of a red high chair".
A prompt that already names a palette colour, or none the lexicon knows, is left as it is.

The palette colour a prompt names (written or read) also constrains the colour code: snapping picks
the nearest colour code among the instances wearing that colour (``model.prior.query.colour_wearers``:
captioned with it and, where any is, dominated by it in renders of their own codes), so the query
network chooses which red, never whether red.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

import numpy as np
from matplotlib.colors import CSS4_COLORS, XKCD_COLORS, to_rgb

from model.data.colours import PALETTE, article, colour_names

MAX_WORDS = 3


@functools.cache
def colour_lexicon() -> dict[str, tuple[float, float, float]]:
    """Colour name (lower case, words separated by single spaces) -> sRGB in [0, 1]; a survey
    name wins over a CSS name of the same spelling."""
    lexicon = {name: to_rgb(value) for name, value in CSS4_COLORS.items()}
    lexicon.update({" ".join(re.findall(r"[a-z]+", key.removeprefix("xkcd:"))): to_rgb(value) for key, value in XKCD_COLORS.items()})
    return lexicon


@dataclass(frozen=True)
class PromptColour:
    """What was read from a prompt: the prompt to embed, the palette colour it names (written, or
    read from a lexicon name; None if neither) and the lexicon name that was replaced, if any."""

    prompt: str
    palette: str | None = None
    name: str | None = None


def palette_prompt(prompt: str) -> PromptColour:
    """``prompt`` with a lexicon colour name replaced by its palette colour (see the module
    docstring); the article before it follows the new word."""
    words = [(m.group().lower(), m.start(), m.end()) for m in re.finditer(r"[A-Za-z]+", prompt)]
    written = next((word for word, _, _ in words if word in PALETTE), None)
    if written is not None:
        return PromptColour(prompt, written)
    lexicon = colour_lexicon()
    for length in range(min(MAX_WORDS, len(words)), 0, -1):
        for first in range(len(words) - length + 1):
            run = words[first : first + length]
            name = " ".join(w for w, _, _ in run)
            if name not in lexicon:
                continue
            palette = colour_names(np.array([lexicon[name]]))[0]
            start, end = run[0][1], run[-1][2]
            before = prompt[:start]
            if first > 0 and words[first - 1][0] in ("a", "an"):
                a_start, a_end = words[first - 1][1], words[first - 1][2]
                chosen = article(palette)
                before = prompt[:a_start] + (chosen.capitalize() if prompt[a_start].isupper() else chosen) + prompt[a_end:start]
            return PromptColour(before + palette + prompt[end:], palette, name)
    return PromptColour(prompt)
