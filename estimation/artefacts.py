"""The names of what a reconstruction writes into its output folder: one spelling for the pipeline, the
exporters, the NeRF readers and the service (this module imports nothing, so the API process can use it
without loading OpenCV or GTSAM)."""

SPARSE_DIR = "sparse"
MODELS_DIR = "models"
"""With export_all_models, model k >= 2 (largest first) goes to OUT/models/<k>/ (the largest is OUT/)."""
PLY_NAME = "points.ply"
TRANSFORMS_NAME = "transforms.json"
REPORT_NAME = "report.json"
DEPTHS_NAME = "depths.npz"
FIGURES_DIR = "figures"
FRAMES_DIR = "frames"
"""A video's keyframes, as images, under OUT/ (transforms.json points at them there)."""
