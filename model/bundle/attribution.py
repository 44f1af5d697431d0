"""Who made the training data: one attribution record per training instance, read from the
dataset's ``index.json`` (the on-disk format of ``model.data.dataset``).

Sweet Home 3D furniture is CC0 or CC-BY 3.0; CC-BY asks for the creator, the licence and a note
of changes, so a record carries the creator, the licence and its URL, the source library and
model file, and says when an instance is a recoloured variant of the original model. Keys the
index does not hold (procedural objects have no creator or licence) are ``null``, never guessed.
"""

from __future__ import annotations

from pathlib import Path

from model.data.dataset import ObjectEntry, load_index


def attribution_record(entry: ObjectEntry) -> dict:
    """``{id, name, creator, licence, licence_url, source, library, model, changes}`` of one dataset object."""
    extra = entry.extra
    variant = extra.get("variant", 0)
    return {
        "id": entry.id,
        "name": extra.get("name") or entry.caption,
        "creator": extra.get("creator"),
        "licence": extra.get("license"),
        "licence_url": extra.get("license_url"),
        "source": extra.get("source"),
        "library": extra.get("library"),
        "model": extra.get("model") or extra.get("file"),
        "changes": f"colours and materials changed (variant {variant} of {extra.get('shape_id', entry.id)})" if variant else None,
    }


def training_attribution(data: Path, instance_ids: list[str]) -> list[dict]:
    """The attribution of each of ``instance_ids``, in that order, from ``data/index.json``."""
    index = {entry.id: entry for entry in load_index(Path(data))}
    missing = [i for i in instance_ids if i not in index]
    if missing:
        raise ValueError(
            f"{len(missing)} instances of the prior (first {missing[0]!r}) are not in {Path(data) / 'index.json'}; "
            "pass --data with the dataset the prior was trained on"
        )
    return [attribution_record(index[i]) for i in instance_ids]
