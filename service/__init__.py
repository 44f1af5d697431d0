"""The hypnerf HTTP service (FastAPI): a bundle kept resident, generated NeRFs cached by content,
renders, meshes, text-to-NeRF, retrieval and inversion jobs. ``service.app.create_app`` builds it."""
