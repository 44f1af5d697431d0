"""Pydantic models of the HTTP API (requests, query parameters, responses), one module per resource."""
