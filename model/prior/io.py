"""The trained prior's file format: ``hypernet.safetensors`` (weights, half precision by default)
and ``prior.json`` (the hypernetwork config, the instances with their captions and shape indices,
the category's camera and scene box, provenance). Weights are safetensors, never pickle.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from model.data.category import CategoryData
from model.nerf import config
from model.nerf.scene import SceneBox
from model.prior.hypernet import HyperNetConfig, HyperNetwork

PRIOR_WEIGHTS = "hypernet.safetensors"
PRIOR_META = "prior.json"


@dataclass
class Prior:
    """A loaded prior: the hypernetwork (float32, eval mode), its category's scene box and metadata."""

    net: HyperNetwork
    scene: SceneBox
    meta: dict

    @property
    def instances(self) -> list[dict]:
        return self.meta["instances"]

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def instance_number(self, instance_id: str) -> int:
        ids = [inst["id"] for inst in self.instances]
        if instance_id not in ids:
            raise ValueError(f"{instance_id!r} is not an instance of this prior; its instances are listed in {PRIOR_META}")
        return ids.index(instance_id)


def export_prior(run: Path, net: HyperNetwork, data: CategoryData, extra: dict, dtype=torch.float16) -> Path:
    """Write the trained prior into ``run``: weights in ``dtype`` and the metadata (plus ``extra``)."""
    tensors = {k: v.detach().to(dtype if v.is_floating_point() else v.dtype).contiguous().cpu() for k, v in net.state_dict().items()}
    save_file(tensors, str(run / PRIOR_WEIGHTS))
    meta = {
        "hypernet": config.to_dict(net.cfg),
        "data": str(data.root),
        "instances": [inst.to_json() for inst in data.instances],
        "camera": config.to_dict(data.camera),
        "scene_box": data.scene.to_aabb(),
        "weights_dtype": str(dtype).removeprefix("torch."),
        **extra,
    }
    (run / PRIOR_META).write_text(json.dumps(meta, indent=2))
    return run / PRIOR_WEIGHTS


def load_prior(run: Path, device=None) -> Prior:
    """The exported prior of a training run, weights promoted to float32."""
    run = Path(run)
    if not (run / PRIOR_WEIGHTS).is_file():
        raise FileNotFoundError(f"{run} holds no trained prior ({PRIOR_WEIGHTS}); run `hypnerf train` to the end first")
    meta = json.loads((run / PRIOR_META).read_text())
    if "scene_box" not in meta:
        raise ValueError(f"{run / PRIOR_META} lacks 'scene_box'; add the training data's aabb, e.g. \"scene_box\": [[-0.5,-0.5,-0.5],[0.5,0.5,0.5]]")
    cfg = config.from_dict(HyperNetConfig, meta["hypernet"])
    instances = meta["instances"]
    net = HyperNetwork(cfg, len(instances), [i["shape_index"] for i in instances])
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in load_file(str(run / PRIOR_WEIGHTS)).items()}
    net.load_state_dict(state)
    return Prior(net.to(device or "cpu").eval(), SceneBox.from_aabb(meta["scene_box"]), meta)
