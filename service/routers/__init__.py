"""HTTP routers, one per resource; each module exposes ``router``."""
