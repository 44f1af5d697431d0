"""The query network and what uses it: embedders loaded offline from their packages, the joint
embedding and its file format, retrieval, codes, sampling, captions, segmentation, and the
commands on the tiny prior."""

from __future__ import annotations

import json
import random

import numpy as np
import pytest
import torch

from model.prior.captions import (
    HELD_OUT_TEMPLATES,
    attributes,
    held_out_prompt,
    object_type,
    training_captions,
)
from model.prior.query import (
    InputSlot,
    QueryConfig,
    QueryNetwork,
    instance_bank,
    load_query,
    nearest_instances,
    retrieve,
    save_query,
    snap_codes,
)
from model.prior.sampling import (
    CodeDensity,
    DensityConfig,
    interpolate,
    nearest_code_distance,
)


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HYPNERF_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def _net(seed: int = 0) -> QueryNetwork:
    torch.manual_seed(seed)
    slots = [InputSlot("img", ("image",), 6, 0, "v1"), InputSlot("txt", ("text",), 4, 6, "v1")]
    return QueryNetwork(QueryConfig(hidden=16, layers=1, dropout=0.0, head="regression"), slots, shape_dim=3, color_dim=2, meta={"embedders": ["img", "txt"]})


# ---------------------------------------------------------------------------------------------
# Embedders (real packaged weights, no network)


def test_efficientnet_lite0_loads_its_packaged_weights_and_sees_a_chair():
    from model.data.cameras import look_at, spherical_direction
    from model.data.meshes import normalise
    from model.data.raycast import render_views
    from model.data.synth import chair_mesh, sample_spec
    from model.prior.embedders import ImageEmbedder

    embedder = ImageEmbedder()
    mesh = normalise(chair_mesh(sample_spec(np.random.default_rng([5, 0]))))
    image = torch.from_numpy(render_views(mesh, look_at(2.0 * spherical_direction(25, -60))[None], 96, 96, 96.0)).float() / 255.0
    top5 = embedder.classify(image)[0].topk(5).indices.tolist()
    assert 559 in top5  # ImageNet "folding chair": wrong padding, normalisation or weights lose it
    features = embedder.embed(torch.cat([image, image.flip(2)]))
    assert features.shape == (2, 1280) and torch.allclose(features.norm(dim=1), torch.ones(2), atol=1e-5)
    assert float(features[0] @ features[1]) > 0.8  # a mirrored view is the same object


def test_same_padding_matches_tensorflow_output_sizes():
    from model.prior.embedders import SameConv2d

    conv = SameConv2d(1, 1, 3, stride=2, bias=False)
    assert conv(torch.zeros(1, 1, 7, 8)).shape[-2:] == (4, 4)
    assert SameConv2d(1, 1, 5, stride=1, bias=False)(torch.zeros(1, 1, 9, 9)).shape[-2:] == (9, 9)


def test_minilm_loads_offline_and_ranks_paraphrases():
    from model.prior.embedders import TextEmbedder

    embedder = TextEmbedder()
    red, crimson, blue = embedder.embed(["a red armchair", "a crimson armchair", "a blue stool"])
    assert torch.allclose(red.norm(), torch.tensor(1.0), atol=1e-5)
    assert float(red @ crimson) > float(red @ blue)
    with pytest.raises(ValueError, match="prompt is empty"):
        embedder.embed(["   "])


def test_clip_without_local_weights_says_what_to_do(monkeypatch, tmp_path):
    from model.prior.embedders import CLIP_WEIGHTS_ENV, EmbedderError, load_embedder

    monkeypatch.delenv(CLIP_WEIGHTS_ENV, raising=False)
    with pytest.raises(EmbedderError, match="nothing is downloaded"):
        load_embedder("clip")
    with pytest.raises(EmbedderError, match="do not exist"):
        load_embedder("clip", clip_weights=tmp_path / "missing.bin")
    with pytest.raises(EmbedderError, match="unknown embedder"):
        load_embedder("resnet")


def test_object_crop_centres_the_object_and_rejects_an_empty_mask():
    from model.prior.embedders import EmbedderError, object_crop, prepare_images

    rgba = torch.zeros(40, 60, 4)
    rgba[10:20, 30:50] = torch.tensor([1.0, 0.0, 0.0, 1.0])
    crop = object_crop(rgba)
    assert crop.shape[0] == crop.shape[1] and crop.shape[0] >= 20
    assert float(crop[..., 3].mean()) > 0.2  # the object fills the crop, not a corner of it
    prepared = prepare_images(rgba[None], 32)
    assert prepared.shape == (1, 3, 32, 32) and float(prepared.min()) >= 0.0
    assert torch.allclose(object_crop(torch.ones(5, 5, 4)), torch.ones(5, 5, 4))  # no mask: the whole image
    with pytest.raises(EmbedderError, match="mask\\) is empty"):
        object_crop(torch.zeros(8, 8, 4))
    with pytest.raises(EmbedderError, match="NaN"):
        prepare_images(torch.full((1, 4, 4, 4), float("nan")), 8)


def test_a_query_image_and_its_mirror_embed_alike():
    from model.prior.embedders import embed_images, embed_queries, load_embedder

    embedder = load_embedder("efficientnet-lite0")
    rgba = torch.zeros(2, 48, 48, 4)
    rgba[:, 8:40, 6:20] = torch.tensor([0.8, 0.2, 0.1, 1.0])  # off-centre, so the mirror differs
    rgba[1, 20:30, 20:44] = torch.tensor([0.1, 0.3, 0.9, 1.0])
    queries = embed_queries(embedder, rgba)
    assert queries.shape == (2, embedder.dim) and torch.allclose(queries.norm(dim=-1), torch.ones(2), atol=1e-5)
    assert torch.allclose(embed_queries(embedder, rgba.flip(2)), queries, atol=1e-5)
    plain, mirrored = embed_images(embedder, rgba), embed_images(embedder, rgba.flip(2))
    assert not torch.allclose(plain, mirrored, atol=1e-3)
    assert torch.allclose(queries, torch.nn.functional.normalize(plain + mirrored, dim=-1), atol=1e-5)


def test_embeddings_are_cached_by_what_changes_them(tmp_path, chairs):
    from model.prior.embedding_cache import view_embeddings

    class Counting:
        name, dim, modalities = "count", 2, ("image",)

        def __init__(self, version):
            self.calls, self._version = 0, version

        def version(self):
            return self._version

        def embed(self, rgba):
            self.calls += 1
            return rgba[..., :2].mean(dim=(1, 2))

    folder = chairs / sorted(p.name for p in chairs.iterdir() if p.is_dir())[0]
    first = Counting("a")
    one = view_embeddings(first, folder, "train", 3)
    assert torch.equal(view_embeddings(first, folder, "train", 3), one) and first.calls == 1
    second = Counting("b")
    view_embeddings(second, folder, "train", 3)
    view_embeddings(second, folder, "train", 4)
    assert second.calls == 2 and one.shape == (3, 2)


# ---------------------------------------------------------------------------------------------
# The query network


def test_joint_embedding_fills_only_the_given_slots():
    net = _net()
    joint = net.joint(text=torch.ones(2, 4))
    assert joint.shape == (2, 10) and float(joint[:, :6].abs().sum()) == 0.0 and float(joint[:, 6:].sum()) == 8.0
    with pytest.raises(ValueError, match="must be \\[B, 6\\]"):
        net.joint(image=torch.ones(2, 5))
    with pytest.raises(ValueError, match="not 'audio'"):
        net.joint(audio=torch.ones(1, 3))
    with pytest.raises(ValueError, match="joint embeddings \\[B, 10\\]"):
        net(torch.ones(1, 9))


def test_outputs_are_at_the_codebook_scale_and_survive_a_round_trip(tmp_path):
    net = _net()
    shapes, colors = torch.randn(5, 3) * 4 + 10, torch.randn(5, 2) * 0.1 - 3
    net.set_code_statistics(shapes, colors)
    torch.nn.init.zeros_(net.mlp[-1].weight)
    torch.nn.init.zeros_(net.mlp[-1].bias)
    shape, color = net(torch.randn(3, 10))
    assert torch.allclose(shape, shapes.mean(0).expand(3, -1), atol=1e-5) and torch.allclose(color, colors.mean(0).expand(3, -1), atol=1e-5)
    torch.nn.init.normal_(net.mlp[-1].weight)
    save_query(tmp_path / "q", net.eval(), {"note": "x"})
    back = load_query(tmp_path / "q")
    x = torch.randn(4, 10)
    assert all(torch.allclose(a, b) for a, b in zip(net(x), back(x)))
    assert back.meta["embedders"] == ["img", "txt"] and back.meta["note"] == "x" and back.modalities == ("image", "text")
    meta = json.loads((tmp_path / "q" / "query.json").read_text())
    meta["format"] = 99
    (tmp_path / "q" / "query.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="newer than this code"):
        load_query(tmp_path / "q")
    with pytest.raises(FileNotFoundError, match="train-query"):
        load_query(tmp_path / "nothing")


def test_codebook_head_outputs_codebook_entries(tmp_path):
    slots = [InputSlot("img", ("image",), 6, 0, "v1")]
    with pytest.raises(ValueError, match="codebook sizes"):
        QueryNetwork(QueryConfig(hidden=8, layers=1, head="codebook"), slots, 3, 2)
    with pytest.raises(ValueError, match="unknown query head"):
        QueryConfig(head="mixture")
    net = QueryNetwork(QueryConfig(hidden=8, layers=1, dropout=0.0, head="codebook"), slots, 3, 2, codebook=(4, 5))
    shapes, colors = torch.randn(4, 3), torch.randn(5, 2)
    net.set_code_statistics(shapes, colors)
    with torch.no_grad():
        net.mlp[-1].weight.zero_()
        net.mlp[-1].bias.copy_(torch.tensor([0, 0, 9.0, 0, 0, 0, 0, 0, 9.0]))
    shape, color = net.eval()(torch.randn(2, 6))
    assert torch.allclose(shape, shapes[2].expand(2, -1), atol=1e-4) and torch.allclose(color, colors[4].expand(2, -1), atol=1e-4)
    save_query(tmp_path / "q", net)
    back = load_query(tmp_path / "q")
    assert back.codebook_sizes == (4, 5) and torch.allclose(back(torch.ones(1, 6))[0], shape[:1], atol=1e-4)


def test_shape_codebook_head_classifies_the_shape_and_regresses_the_colour(tmp_path):
    slots = [InputSlot("img", ("image",), 6, 0, "v1")]
    with pytest.raises(ValueError, match="codebook sizes"):
        QueryNetwork(QueryConfig(hidden=8, layers=1, head="shape-codebook"), slots, 3, 2)
    net = QueryNetwork(QueryConfig(hidden=8, layers=1, dropout=0.0, head="shape-codebook"), slots, 3, 2, codebook=(4, 5))
    shapes, colors = torch.randn(4, 3), torch.randn(5, 2)
    net.set_code_statistics(shapes, colors)
    assert net.mlp[-1].out_features == 4 + 2 and not hasattr(net, "color_book")
    with torch.no_grad():
        net.mlp[-1].weight.zero_()
        net.mlp[-1].bias.copy_(torch.tensor([0, 9.0, 0, 0, 1.5, -0.5]))
    shape, color = net.eval()(torch.randn(2, 6))
    assert torch.allclose(shape, shapes[1].expand(2, -1))
    expected = torch.tensor([1.5, -0.5]) * colors.std(0, unbiased=False) + colors.mean(0)  # standardised units back to codes
    assert torch.allclose(color, expected.expand(2, -1), atol=1e-5)
    save_query(tmp_path / "q", net)
    back = load_query(tmp_path / "q")
    assert back.cfg.head == "shape-codebook" and all(torch.allclose(a, b) for a, b in zip(back(torch.ones(1, 6)), net(torch.ones(1, 6))))


def test_retrieve_ranks_by_cosine_and_rejects_bad_shapes():
    bank = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.7, 0.7]])
    indices, scores = retrieve(torch.tensor([2.0, 0.1]), bank, k=2)
    assert indices.tolist() == [0, 2] and scores[0] > scores[1] and float(scores[0]) <= 1.0 + 1e-6
    assert len(retrieve(torch.tensor([0.0, 1.0]), bank, k=10)[0]) == 3
    with pytest.raises(ValueError, match="bank \\[N, E\\]"):
        retrieve(torch.ones(3), bank)
    with pytest.raises(ValueError, match="empty"):
        retrieve(torch.ones(2), torch.zeros(0, 2))
    views = torch.randn(4, 3, 8)
    assert torch.allclose(instance_bank(views).norm(dim=1), torch.ones(4), atol=1e-5)


def test_snapping_and_nearest_instances_use_the_codebook():
    net = _net()
    shapes, colors = torch.randn(6, 3), torch.randn(6, 2)
    net.set_code_statistics(shapes, colors)
    shape, color = shapes[[4]] + 0.01, colors[[1]] - 0.01
    snapped_shape, snapped_color = snap_codes(net, shape, color, shapes, colors)
    assert torch.equal(snapped_shape, shapes[[4]]) and torch.equal(snapped_color, colors[[1]])
    assert nearest_instances(net, shapes[[2]], colors[[2]], shapes, colors, k=3)[0, 0] == 2
    # a colour the prompt names restricts the colour to its wearers; the shape is untouched
    from model.prior.query import code_distances, colour_rows, instance_colours

    instances = instance_colours([{"caption": f"a {c} chair"} for c in ("red", "blue", "red", "green", "blue", "red")])
    wearers = colour_rows(instances, "blue")
    assert wearers.tolist() == [False, True, False, False, True, False] and colour_rows(instances, None) is None
    assert instance_colours([{"caption": "a chair"}, {}]) == [None, None]
    _, blue = snap_codes(net, shape, colors[[0]], shapes, colors, wearers)
    distances = code_distances(net, shape, colors[[0]], shapes, colors)[1][0]
    assert torch.equal(blue, colors[[1 if distances[1] < distances[4] else 4]])
    assert torch.equal(snap_codes(net, shape, colors[[0]], shapes, colors, wearers)[0], shapes[[4]])
    # no instance wears it: the whole codebook
    assert torch.equal(snap_codes(net, shape, colors[[0]], shapes, colors, colour_rows(instances, "pink"))[1], colors[[0]])


# ---------------------------------------------------------------------------------------------
# Sampling, captions, segmentation


def test_interpolation_and_density_samples():
    a, b = torch.zeros(4), torch.ones(4)
    path = interpolate(a, b, 5)
    assert torch.equal(path[0], a) and torch.equal(path[-1], b) and torch.allclose(path[2], torch.full((4,), 0.5))
    with pytest.raises(ValueError, match="at least 2 steps"):
        interpolate(a, b, 1)
    generator = torch.Generator().manual_seed(0)
    shapes = torch.cat([torch.randn(10, 4, generator=generator) * 0.1 + 3, torch.randn(10, 4, generator=generator) * 0.1 - 3])
    colors = torch.randn(20, 3, generator=generator)
    density = CodeDensity.fit(shapes, colors, DensityConfig(seed=0))
    assert len(density.shape.weights) >= 2  # two clusters of shapes: BIC picks more than one component
    s1, c1 = density.sample(8, seed=3)
    s2, _ = CodeDensity.from_json(json.loads(json.dumps(density.to_json()))).sample(8, seed=3)
    assert s1.shape == (8, 4) and c1.shape == (8, 3) and torch.allclose(s1, s2)
    assert float(s1[:, 0].abs().min()) > 1.5  # samples stay in the clusters, not between them
    relative, index = nearest_code_distance(shapes[:3], shapes)
    assert torch.allclose(relative, torch.zeros(3)) and index.tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="NaN"):
        CodeDensity.fit(torch.full((4, 2), float("nan")), colors)


def test_captions_paraphrase_attributes_and_held_out_prompts_are_new():
    entry = {"caption": "a brown winchester armchair", "category": "chair", "name": "Winchester armchair"}
    attrs = attributes(entry)
    assert attrs.colour == "brown" and attrs.kind == "armchair" and attrs.noun == "winchester armchair"
    texts = training_captions(entry["caption"], attrs)
    assert "a brown armchair" in texts and entry["caption"] in texts and len(texts) == len(set(texts))
    assert object_type("Bar stool") == "stool" and object_type("Deck chair") == "lounge chair" and object_type("Oak chair") == "chair"
    assert attributes({"caption": "a red chair with arms", "category": "chair", "attributes": {"arms": True}}).kind == "armchair"
    rng = random.Random(0)
    prompts = {held_out_prompt("brown", "armchair", rng) for _ in range(20)}
    synonyms = {held_out_prompt("brown", "armchair", rng, synonym=True) for _ in range(20)}
    assert not (prompts | synonyms) & set(texts) and all("brown" in p for p in prompts) and all("brown" not in p for p in synonyms)
    assert len(HELD_OUT_TEMPLATES) >= 3


def test_training_words_are_disjoint_from_held_out_words():
    from model.data.colours import PALETTE
    from model.prior.captions import (
        COLOUR_SYNONYMS,
        TRAIN_COLOUR_WORDS,
        TRAIN_TYPE_WORDS,
        TYPE_WORDS,
    )

    held_colours = {w for words in COLOUR_SYNONYMS.values() for w in words}
    train_colours = {w for words in TRAIN_COLOUR_WORDS.values() for w in words}
    assert set(TRAIN_COLOUR_WORDS) == set(PALETTE) == set(COLOUR_SYNONYMS)
    assert not held_colours & train_colours and not train_colours & set(PALETTE)
    held_types = {w for kind, words in TYPE_WORDS.items() for w in words if w != kind}  # the type names themselves are trained on
    assert not held_types & {w for words in TRAIN_TYPE_WORDS.values() for w in words}
    assert set(TRAIN_TYPE_WORDS) == set(TYPE_WORDS)


def test_colour_vocabulary_files_survey_names_under_their_colour_and_never_a_held_out_word():
    from matplotlib.colors import XKCD_COLORS, to_rgb

    from model.data.colours import PALETTE, colour_names
    from model.prior.captions import COLOUR_SYNONYMS, colour_vocabulary

    vocabulary = colour_vocabulary()
    assert set(vocabulary) == set(PALETTE)
    assert all(len(words) >= 4 for words in vocabulary.values()) and sum(map(len, vocabulary.values())) > 300
    held = {w for words in COLOUR_SYNONYMS.values() for w in words}
    every = [w for words in vocabulary.values() for w in words]
    assert len(every) == len(set(every))
    assert not [w for w in every if any(h in w for h in held)]
    assert "creme" not in every  # a near-spelling of the held-out "cream"
    for colour, words in vocabulary.items():
        assert colour in words  # the palette name is a survey name filed under itself
        measured = colour_names(np.array([to_rgb(XKCD_COLORS["xkcd:" + w]) for w in words]))
        assert set(measured) == {colour}
        # a name's own palette word never contradicts where it is filed
        assert not [w for w in words if any(p in w.split() for p in PALETTE if p != colour) and colour not in w.split()]


def test_vocabulary_captions_name_the_colour_by_its_vocabulary():
    from model.prior.captions import colour_vocabulary, vocabulary_captions
    from model.train.query import caption_targets

    nouns = ["stool", "bar stool"]
    texts = vocabulary_captions(nouns, "green", 40, random.Random(3))
    assert len(texts) == 40 and texts == vocabulary_captions(nouns, "green", 40, random.Random(3))
    words = colour_vocabulary()["green"]
    assert all(any(w in t for w in words) and any(n in t for n in nouns) for t in texts)
    assert len({t for t in texts}) > 20  # words and templates vary
    assert not set(texts) & {held_out_prompt("green", "stool", random.Random(k), synonym=s) for k in range(30) for s in (False, True)}
    entries = [
        {"caption": "a red armchair", "category": "chair", "name": "Club armchair"},
        {"caption": "a green stool", "category": "chair", "name": "Bar stool"},
    ]
    base = caption_targets(entries, [0, 1], composed_per_pair=2, seed=0)
    texts, owners = caption_targets(entries, [0, 1], composed_per_pair=2, seed=0, vocabulary=5)
    assert len(texts) == len(base[0]) + 2 * 5 + 2 * 5  # each instance and each composed pair
    kept = [(t, o) for t, o in zip(texts, owners) if t in base[0]]
    assert kept == list(zip(*base))  # the other captions and their targets do not change
    extra = [(t, o) for t, o in zip(texts, owners) if t not in base[0]]
    vocab = colour_vocabulary()
    for text, (shape, colour_owner) in extra:
        colour = entries[colour_owner]["caption"].split()[1]
        assert any(w in text for w in vocab[colour])
        assert ("stool" in text) == (shape == 1)


@pytest.mark.parametrize("prompt, read_as, name, palette", [
    ("a photo of a crimson high chair", "a photo of a red high chair", "crimson", "red"),
    ("An amber stool", "A yellow stool", "amber", "yellow"),  # the article follows the new word
    ("a 3d model of a dusty rose chair", "a 3d model of a pink chair", "dusty rose", "pink"),  # the longest name wins
    ("I would like an armchair painted gray", "I would like an armchair painted grey", "gray", "grey"),
    ("a red leather armchair", "a red leather armchair", None, "red"),  # a palette word is kept, and nothing else read
    ("render a jet folding chair", "render a black folding chair", "jet", "black"),  # not a survey name: WordNet's
    ("an ebony stool", "a black stool", "ebony", "black"),
    ("a walnut chair", "a walnut chair", None, None),  # a colour name neither source knows
    ("a classic garden chair", "a classic garden chair", None, None),  # ordinary words are no colours
    ("a chair for my living room", "a chair for my living room", None, None),
    ("", "", None, None),
])
def test_a_colour_name_is_read_as_its_palette_colour(prompt, read_as, name, palette):
    from model.prior.colour_words import palette_prompt

    read = palette_prompt(prompt)
    assert (read.prompt, read.name, read.palette) == (read_as, name, palette)


def test_the_colour_lexicon_reads_names_by_their_colour_not_their_spelling():
    from model.data.colours import PALETTE
    from model.prior.colour_words import PromptColour, colour_lexicon, palette_prompt

    lexicon = colour_lexicon()
    assert len(lexicon) > 1000 and all(0.0 <= v <= 1.0 for rgb in lexicon.values() for v in rgb)
    assert all(palette_prompt(f"a {c} chair") == PromptColour(f"a {c} chair", c) for c in PALETTE)
    # the survey's navy (#01153e) is nearer the palette's black than its blue in CIELAB; "navy blue"
    # names a palette word and is left as it is
    assert palette_prompt("a navy chair").palette == "black" and palette_prompt("a navy blue chair").name is None
    assert palette_prompt("a navy blue chair").palette == "blue"
    assert palette_prompt("a chartreuse chair").palette == "yellow"


def test_the_wordnet_colour_table_is_what_wordnet_gives():
    from model.prior.colour_words import wordnet_colour_table, wordnet_colours

    committed = wordnet_colours()
    assert wordnet_colour_table() == committed, "rebuild it: python -m model.prior.colour_words"
    assert len(committed) > 300 and set(committed.values()) <= set(__import__("model.data.colours", fromlist=["PALETTE"]).PALETTE)
    # senses read through the hypernyms: a coal black is a black, a bone a white, a dark blue a blue
    assert (committed["ebony"], committed["ivory"], committed["navy"]) == ("black", "white", "blue")
    # words WordNet gives no colour sense are not in it, however a colour-name list spells them
    assert not {"garden", "classic", "vintage", "create", "easy", "metal", "wood", "chair", "stool"} & committed.keys()


def test_no_prompt_template_or_type_word_reads_as_a_colour():
    import re

    from model.prior.captions import HELD_OUT_TEMPLATES, TRAIN_TYPE_WORDS, TYPE_WORDS
    from model.prior.colour_words import palette_prompt

    words = {w for t in HELD_OUT_TEMPLATES for w in re.findall(r"[a-z]+", t.lower())}
    words |= {w for table in (TYPE_WORDS, TRAIN_TYPE_WORDS) for kind, names in table.items() for w in re.findall(r"[a-z]+", " ".join((kind, *names)))}
    assert [w for w in sorted(words) if palette_prompt(f"a {w}").palette is not None] == []


def test_composed_captions_aim_at_the_shape_and_a_wearer_of_the_colour():
    from model.prior.captions import composed_captions
    from model.train.query import caption_targets

    entries = [
        {"caption": "a red armchair", "category": "chair", "name": "Club armchair"},
        {"caption": "a blue armchair", "category": "chair", "name": "Club armchair"},
        {"caption": "a green stool", "category": "chair", "name": "Bar stool"},
    ]
    shape_of = [0, 0, 1]
    texts, owners = caption_targets(entries, shape_of, composed_per_pair=3, seed=0)
    own = [(t, o) for t, o in zip(texts, owners) if o[0] == o[1]]
    composed = [(t, o) for t, o in zip(texts, owners) if o[0] != o[1]]
    assert {o[0] for _, o in own} == {0, 1, 2}
    # the armchair shape in green (worn by the stool) and the stool in red or blue, never a colour its own instances wear
    assert {(o[0], entries[o[1]]["caption"].split()[1]) for _, o in composed} == {(0, "green"), (2, "red"), (2, "blue")}
    for text, (shape, donor) in composed:
        assert text in composed_captions(attributes(entries[shape]), entries[donor]["caption"].split()[1])
    assert len(composed) == 3 * 3
    assert caption_targets(entries, shape_of, 3, seed=0) == (texts, owners)  # seeded
    assert all(o[0] == o[1] for o in caption_targets(entries, shape_of, 0)[1])
    with pytest.raises(ValueError, match="palette"):
        composed_captions(attributes(entries[0]), "chartreuse")


def test_segmentation_accepts_alpha_and_masks_and_segments_a_plain_photo():
    from model.nerf.segment import SegmentationError, object_rgba

    rng = np.random.default_rng(0)
    photo = np.clip(0.85 + 0.03 * rng.standard_normal((64, 64, 3)), 0, 1).astype(np.float32)
    yy, xx = np.mgrid[:64, :64]
    disc = (yy - 30) ** 2 + (xx - 34) ** 2 < 15**2
    photo[disc] = (0.7, 0.1, 0.1)
    rgba, how = object_rgba(photo)
    assert how == "grabcut"
    found = rgba[..., 3] > 0.5
    assert (found & disc).sum() / (found | disc).sum() > 0.9
    masked, how = object_rgba((photo * 255).astype(np.uint8), mask=disc.astype(np.uint8) * 255)
    assert how == "mask" and np.array_equal(masked[..., 3] > 0.5, disc)
    with_alpha = np.concatenate([photo, disc[..., None].astype(np.float32)], axis=-1)
    assert object_rgba(with_alpha)[1] == "alpha"
    with pytest.raises(SegmentationError, match="could not separate the object.*with a mask"):
        object_rgba(np.full((64, 64, 3), 0.5, np.float32))
    boxed, _ = object_rgba(photo, box=(15, 11, 54, 50))
    inside = np.zeros_like(disc)
    inside[11:50, 15:54] = True
    assert (boxed[..., 3] > 0.5)[disc].mean() > 0.9 and not (boxed[..., 3] > 0.5)[~inside].any()
    with pytest.raises(SegmentationError, match="leaves no part"):
        object_rgba(photo, box=(70, 70, 90, 90))
    with pytest.raises(SegmentationError, match="image's size"):
        object_rgba(photo, mask=np.ones((10, 10)))
    with pytest.raises(SegmentationError, match="\\[H, W, 3\\]"):
        object_rgba(np.zeros((4, 64, 64, 3)))


# ---------------------------------------------------------------------------------------------
# End to end on the tiny prior


@pytest.fixture(scope="module")
def query_run(trained, chairs, tmp_path_factory):
    from model.train.query import QueryTrainConfig, train_query

    run, _ = trained
    out = tmp_path_factory.mktemp("query")
    cfg = QueryTrainConfig(query=QueryConfig(hidden=64, layers=1), views_per_instance=4, validation_views=1, steps=100, batch=64)
    summary = train_query(run, chairs, out, cfg, progress=False)
    return run, out, summary


def test_training_writes_a_network_that_retrieves_its_instances(query_run, chairs):
    from model.prior.query import QueryPipeline

    run, out, summary = query_run
    instances = summary["instances"]
    assert instances >= 4 and summary["captions"] > instances
    assert summary["validation"]["top1"] > 1 / instances  # better than chance on held-out views
    pipeline = QueryPipeline.from_runs(run, out)
    assert pipeline.net.meta["embedders"] == ["efficientnet-lite0", "minilm"]
    shape, color = pipeline.codes(pipeline.embed(text="a red chair"), snap=True)
    assert any(torch.equal(shape[0], row) for row in pipeline.shape_book)
    assert torch.isfinite(color).all()


def test_text_and_sample_commands_write_their_outputs(query_run, tmp_path):
    from model.cli.main import main

    run, query, _ = query_run
    out = tmp_path / "text"
    assert main(["text", "a blue chair", "--run", str(run), "--query", str(query), "--out", str(out), "--frames", "2", "--res", "24", "--mesh-resolution", "24"]) == 0
    meta = json.loads((out / "nerf.json").read_text())
    assert meta["prompt"] == "a blue chair" and {"embedding_ms", "query_ms", "hypernetwork_ms", "first_render_ms"} <= set(meta["timings"])
    assert (out / "turntable.gif").is_file() and (out / "mesh.glb").is_file() and (out / "renders").is_dir()
    assert main(["text", " ", "--run", str(run), "--query", str(query), "--out", str(out)]) == 2
    samples = tmp_path / "samples"
    assert main(["sample", "--run", str(run), "--n", "2", "--out", str(samples), "--frames", "2", "--res", "24", "--mesh-resolution", "24"]) == 0
    record = json.loads((samples / "samples.json").read_text())
    assert len(record["samples"]) == 2 and (samples / "grid.png").is_file() and (samples / "sample_001" / "mesh.glb").is_file()


def test_retrieval_and_text_evaluations_on_the_tiny_prior(query_run, chairs, tmp_path):
    from model.eval.query import retrieval, text_to_nerf
    from model.prior.query import QueryPipeline

    run, query, _ = query_run
    pipeline = QueryPipeline.from_runs(run, query)
    report = retrieval(pipeline, chairs, views_per_instance=1, bank_views=4, resolution=32, grid_png=tmp_path / "r.png")
    assert report["queries"] == report["instances"] == len(pipeline.prior.instances) and 0.0 <= report["top1"] <= report["top3"] <= 1.0
    assert set(report["conditions"]) == {"clean", "cluttered_grabcut_box", "cluttered_grabcut_border", "cluttered_unsegmented"}
    assert report["poses"]["angle_to_nearest_training_view_deg"]["min"] > 0.0 and (tmp_path / "r.png").is_file()
    text = text_to_nerf(pipeline, chairs, prompts=3, grid_png=tmp_path / "t.png")
    assert text["prompts"] == 3 and 0.0 <= text["colour_accuracy"] <= 1.0 and (tmp_path / "t.png").is_file()
    assert all(row["prompt"] not in training_captions("", attributes({"caption": ""})) for row in text["rows"])


def test_sampling_evaluation_reports_distances_and_validity(trained, tmp_path):
    from model.eval.query import sampling
    from model.prior.io import load_prior

    run, _ = trained
    report = sampling(load_prior(run), samples=2, pairs=1, steps=3, grid_png=tmp_path / "s.png", interpolation_png=tmp_path / "i.png")
    assert report["samples"] == 2 and report["distance_to_nearest_training_code"]["shape_median"] >= 0.0
    assert 0.0 <= report["samples_validity"]["haze_fraction"] <= 1.0 and len(report["interpolation"][0]["shape_path_haze"]) == 3
    assert (tmp_path / "s.png").is_file() and (tmp_path / "i.png").is_file()


def test_tto_started_from_the_query_guess(query_run, chairs):
    from model.eval.query import tto_starts
    from model.optimize.tto import TTOConfig
    from model.prior.query import QueryPipeline

    run, query, _ = query_run
    report = tto_starts(QueryPipeline.from_runs(run, query), chairs, objects=1, evaluation_views=2,
                        cfg=TTOConfig(steps=4, rays_per_step=128, init_rays=64, patience=0, progress_every=1))
    starts = report["rows"][0]["starts"]
    assert set(starts) == {"query", "mean", "nearest"} and starts["query"]["init"] == "given" and starts["mean"]["init"] == "mean"
    assert all(s["time_to_target_s"] is not None and s["held_out_psnr"] > 0 for s in starts.values())


def test_invert_command_starts_from_the_query_guess_with_a_mirrored_view_and_a_refined_pose(query_run, chairs, tmp_path):
    from PIL import Image

    from model.cli.main import main
    from model.data.dataset import load_index, load_views
    from model.prior.outputs import load_nerf

    run, query, _ = query_run
    object_id = next(e.id for e in load_index(chairs) if e.split == "test")
    held = load_views(chairs / object_id, "test").subset([0])
    image, pose = tmp_path / "photo.png", tmp_path / "pose.json"
    Image.fromarray((held.images[0].numpy() * 255).round().astype(np.uint8), "RGBA").save(image)
    cam = held.cameras[0]
    pose.write_text(json.dumps({"frames": [{"transform_matrix": held.c2w[0].tolist(), "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy}]}))
    out = tmp_path / "inverted"
    assert main(["invert", "--run", str(run), "--image", str(image), "--pose", str(pose), "--out", str(out), "--init", "query", "--query", str(query),
                 "--mirror", "--refine-pose", "--steps", "6", "--rays", "128", "--mesh-resolution", "16"]) == 0
    _, _, _, _, meta = load_nerf(out / "nerf.safetensors")
    assert meta["codes"]["init"] == "given" and meta["pose"] == "refined" and meta["tto"]["mirror"] is True
    frames = json.loads((out / "pose.json").read_text())["frames"]
    assert len(frames) == 1
    refined = np.array(frames[0]["transform_matrix"])
    # one pose per input image (the mirrored virtual view is not one), moved a little by the refinement
    assert refined.shape == (4, 4) and np.abs(refined - held.c2w[0].numpy()).max() < 0.5


@pytest.mark.parametrize("head, colour_is_an_entry", [("codebook", True), ("shape-codebook", False)])
def test_codebook_heads_train_and_answer_with_codebook_entries(trained, chairs, tmp_path, head, colour_is_an_entry):
    from model.prior.query import QueryPipeline
    from model.train.query import QueryTrainConfig, train_query

    run, _ = trained
    cfg = QueryTrainConfig(query=QueryConfig(hidden=32, layers=1, head=head), views_per_instance=2, validation_views=1, steps=30, batch=32)
    summary = train_query(run, chairs, tmp_path / "q", cfg, progress=False)
    assert summary["final_loss"] > 0 and summary["validation"]["queries"] == summary["instances"]
    pipeline = QueryPipeline.from_runs(run, tmp_path / "q")
    shape, color = pipeline.codes(pipeline.embed(text="a green chair"), snap=False)
    assert any(torch.equal(shape[0], row) for row in pipeline.shape_book)
    # the codebook head picks a colour entry; the shape-codebook head regresses it (snapped only on request)
    assert any(torch.equal(color[0], row) for row in pipeline.color_book) == colour_is_an_entry


# ---------------------------------------------------------------------------------------------
# Colour measure and colour wearers


def test_colour_measure_names_shaded_pixels_by_their_albedo_and_ignores_the_background():
    from model.data.colours import PALETTE
    from model.data.raycast import linear_to_srgb, srgb_to_linear
    from model.prior.colour_measure import (
        IRRADIANCE,
        dominant_colour_of,
        shading_invariant_names,
    )

    red = srgb_to_linear(np.array(PALETTE["red"]))
    shaded = [linear_to_srgb(red * IRRADIANCE[0]), linear_to_srgb(red * IRRADIANCE[1])]
    assert shading_invariant_names(np.stack(shaded)) == ["red", "red"]
    # 3 red foreground pixels, 1 blue one, and blue background (opacity <= 0.5) that must not count
    images = torch.tensor(PALETTE["blue"], dtype=torch.float32).expand(1, 2, 4, 3).clone()
    images[0, 0, :3] = torch.tensor(PALETTE["red"])
    opacity = torch.zeros(1, 2, 4)
    opacity[0, 0] = 1.0
    name, shares = dominant_colour_of(images, opacity)
    assert name == "red" and shares == pytest.approx({"red": 0.75, "blue": 0.25})
    assert dominant_colour_of(images, torch.zeros(1, 2, 4)) == (None, {})


def test_colour_wearers_prefer_the_instances_their_colour_dominates():
    from model.prior.query import colour_rows, colour_wearers

    captions = ["red", "red", "blue", None]
    shares = [{"red": 0.3, "grey": 0.7}, {"red": 0.8, "white": 0.2}, {"grey": 0.6, "blue": 0.4}, {}]
    assert colour_wearers(captions, "red") == [0, 1]
    assert colour_wearers(captions, "red", shares) == [1]
    # no wearer its colour dominates: the captioned ones
    assert colour_wearers(captions, "blue", shares) == [2]
    assert colour_wearers(captions, "pink", shares) == [] and colour_wearers(captions, None, shares) == []
    assert colour_rows(captions, "red", shares).tolist() == [False, True, False, False]
    assert colour_rows(captions, None, shares) is None


def test_rendered_colours_are_measured_per_instance_and_cached_by_the_weights(trained, monkeypatch):
    import model.prior.colour_measure as colour_measure
    from model.prior.io import load_prior

    prior = load_prior(trained[0])
    shares = colour_measure.rendered_colours(prior, resolution=16)
    assert len(shares) == len(prior.instances)
    assert all(not s or sum(s.values()) == pytest.approx(1.0, abs=0.01) for s in shares)
    assert any(shares), "a trained prior renders some foreground"

    def no_render(*args, **kwargs):
        raise AssertionError("the second measurement of the same prior must come from the cache")

    monkeypatch.setattr(colour_measure, "render_codes", no_render)
    assert colour_measure.rendered_colours(prior, resolution=16) == shares
    with torch.no_grad():
        prior.net.color_codes.weight.add_(1.0)  # other weights: another cache entry, measured anew
    with pytest.raises(AssertionError, match="from the cache"):
        colour_measure.rendered_colours(prior, resolution=16)
