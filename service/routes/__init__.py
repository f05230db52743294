"""The /v1 routers of the REST API."""
