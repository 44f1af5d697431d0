"""Multi-view datasets of objects: the on-disk format, ground-truth rendering and the data sources."""
