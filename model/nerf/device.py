"""Device selection at run time: CUDA when present, else CPU; never hard-coded."""

from __future__ import annotations

import os

import torch


def default_device() -> torch.device:
    """The device to compute on; ``HYPNERF_DEVICE`` overrides (``cpu``, ``cuda``, ``cuda:1``)."""
    name = os.environ.get("HYPNERF_DEVICE")
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")
