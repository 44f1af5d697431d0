"""hypnerf's ML core: hash encoding, NeRF field, renderer, per-object fits, datasets, metrics."""
