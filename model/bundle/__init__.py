"""Bundles: a trained prior exported for the service (ONNX graph, safetensors weights, instances,
manifest with hashes and attribution) and its verified loading.

Loading is on the service's start-up path, so importing this package imports only what loading
needs; ``export_bundle`` (the ONNX exporter, the dataset index) is imported on first use.
"""

from model.bundle.load import Bundle, load_bundle
from model.bundle.manifest import BUNDLE_FORMAT, BundleError

__all__ = ["BUNDLE_FORMAT", "Bundle", "BundleError", "export_bundle", "load_bundle"]


def __getattr__(name: str):
    if name == "export_bundle":
        from model.bundle.export import export_bundle

        return export_bundle
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
