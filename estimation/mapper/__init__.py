"""The incremental mapper: initial pair, registration, triangulation and refinement (orchestration only)."""
