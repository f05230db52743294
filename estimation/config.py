"""Typed configuration of a reconstruction, shared by the CLI, the REST service and the tests."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field


class RansacConfig(BaseModel):
    """Robust estimation settings (fundamental matrix and PnP)."""

    threshold_px: float = Field(1.0, gt=0, description="Inlier threshold in pixels (Sampson / reprojection).")
    pnp_threshold_px: float = Field(4.0, gt=0, description="PnP RANSAC inlier threshold in pixels.")
    confidence: float = Field(0.999, gt=0, lt=1, description="Chance of one outlier-free sample.")
    max_iterations: int = Field(5000, ge=1, description="Upper bound on the adaptive iteration count.")
    seed: int = Field(0, description="Seed of the random sampler, for repeatable runs.")


class BundleAdjustmentConfig(BaseModel):
    """Levenberg-Marquardt bundle adjustment settings (GTSAM)."""

    max_iterations: int = Field(100, ge=1, description="Maximum Levenberg-Marquardt iterations.")
    huber_threshold_px: float = Field(2.0, gt=0, description="Huber robust-loss threshold in pixels.")
    measurement_sigma_px: float = Field(1.0, gt=0, description="Std-dev of a pixel measurement.")
    relative_error_tol: float = Field(1e-6, gt=0, description="Stop when the cost changes less than this.")
    local_window: int = Field(3, ge=2, description="Cameras optimised in the local BA after a registration.")


class FilterConfig(BaseModel):
    """Which triangulated points are kept."""

    max_reprojection_px: float = Field(4.0, gt=0, description="Drop points whose error exceeds this.")
    min_triangulation_angle_deg: float = Field(1.0, ge=0, description="Drop points seen at smaller angles.")


class SiftConfig(BaseModel):
    """SIFT features and matching (used when no match files are given)."""

    max_features: int = Field(8000, ge=100, description="Keypoints per image.")
    ratio: float = Field(0.8, gt=0, lt=1, description="Lowe's ratio test threshold.")
    exhaustive_up_to: int = Field(30, ge=2, description="Match all pairs up to this many images.")
    window: int = Field(10, ge=1, description="Otherwise match each image with its next `window` images.")


class ReconstructionConfig(BaseModel):
    """Everything `estimation.reconstruct` needs besides the images folder."""

    features: Literal["auto", "matches", "sift"] = Field(
        "auto", description="auto: match files when the folder has them, else SIFT."
    )
    calibration: Path | None = Field(None, description="3x3 K file; default: calibration.txt in the folder.")
    ransac: RansacConfig = RansacConfig()
    bundle_adjustment: BundleAdjustmentConfig = BundleAdjustmentConfig()
    filter: FilterConfig = FilterConfig()
    sift: SiftConfig = SiftConfig()
    min_initial_pair_inliers: int = Field(30, ge=8, description="Fewest inliers for an initial pair.")
    min_pnp_correspondences: int = Field(6, ge=6, description="Fewest 2D-3D matches to register an image.")
    write_figures: bool = Field(True, description="Write the PNG figures into OUT/figures.")
