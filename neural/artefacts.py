"""The names of what a NeRF run writes into its folder: one spelling for training, inference and the
service (this module imports nothing, so the API process can use it without loading PyTorch)."""

RUN_CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
"""The run's metrics, one JSON object a line."""
IMAGE_CACHE_DIR = "image_cache"
"""Resized training images are cached in this folder of the run (evaluating the run reuses them)."""
