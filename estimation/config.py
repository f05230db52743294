"""Typed configuration of a reconstruction, shared by the CLI, the REST service and the tests."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class StrictConfig(BaseModel):
    """A configuration that refuses unknown fields: a misspelt setting is an error naming it, not a silent
    default (as neural.TrainConfig)."""

    model_config = ConfigDict(extra="forbid")


class RansacConfig(StrictConfig):
    """Robust estimation settings of the RANSAC driver (estimation.geometry.ransac), for every estimator."""

    threshold_px: float = Field(1.0, gt=0, description="Inlier threshold in pixels (Sampson / reprojection).")
    pnp_threshold_px: float = Field(4.0, gt=0, description="PnP RANSAC inlier threshold in pixels.")
    confidence: float = Field(0.999, gt=0, lt=1, description="Chance of one outlier-free sample.")
    min_iterations: int = Field(0, ge=0, description="Lower bound on the adaptive iteration count.")
    max_iterations: int = Field(5000, ge=1, description="Upper bound on the adaptive iteration count.")
    local_refits: int = Field(
        5, ge=0, description="LO-RANSAC: re-fits on the inliers of each new best model (0: none)."
    )
    seed: int = Field(0, description="Seed of the random sampler, for repeatable runs.")


class BundleAdjustmentConfig(StrictConfig):
    """Levenberg-Marquardt bundle adjustment settings (GTSAM)."""

    max_iterations: int = Field(100, ge=1, description="Maximum Levenberg-Marquardt iterations.")
    huber_threshold_px: float = Field(2.0, gt=0, description="Huber robust-loss threshold in pixels.")
    measurement_sigma_px: float = Field(1.0, gt=0, description="Std-dev of a pixel measurement.")
    relative_error_tol: float = Field(1e-6, gt=0, description="Stop when the cost changes less than this.")
    absolute_error_tol: float = Field(0.0, ge=0, description="Stop when the cost decreases less than this.")
    local_window: int = Field(6, ge=2, description="Cameras optimised in the local BA after a registration.")
    local_max_iterations: int = Field(
        2, ge=1, description="Iterations of each local BA with fixed intrinsics (the final BA converges; a "
        "step that raises the cost falls back to LM). 2 instead of 10 (2.4 iterations per local BA at "
        "local_relative_error_tol): lego end to end (bench_sfm.py --seeds 0-19, refinement_max_iterations "
        "1) every seed 90/90, mean of the seeds' mean rotation errors 0.403 deg (10 iterations: 0.402), "
        "worst seed 0.458 (0.457), worst image 3.17 deg (4.67). 1 saved another ~0.16 CPU s per mapping "
        "but put seeds 9, 16, 17 at 0.481, 0.478, 0.497 deg (worst image 7.05 deg).",
    )
    local_max_iterations_refining: int = Field(
        10, ge=1, description="Iterations of each local BA that refines intrinsics: one step there (and in "
        "the refinement BAs) left the self-calibration worse (bench_intrinsics --uncalibrated-only: "
        "fountain-P11's focal +0.38 % off against -0.12 %, 0.109 against 0.044 deg mean rotation error; "
        "Herz-Jesus-P8's +1.21 % against -0.16 %).",
    )
    local_relative_error_tol: float = Field(
        1e-4, gt=0, description="relative_error_tol of each local BA (it stops none at local_max_iterations "
        "1): on lego's 88 local BAs, 1e-4 instead of 1e-6 halves the iterations and leaves 0.003 % more "
        "cost, which the next BAs remove anyway.",
    )
    optimizer: Literal["levenberg_marquardt", "gauss_newton"] = Field(
        "levenberg_marquardt",
        description="GTSAM's nonlinear optimizer. gauss_newton takes undamped steps (no damping factors to "
        "build and eliminate: ~20 % less CPU per iteration on lego's local BAs) and falls back to "
        "levenberg_marquardt from the start when a step raises the cost or the system is indeterminate.",
    )
    mapper_optimizer: Literal["levenberg_marquardt", "gauss_newton"] = Field(
        "gauss_newton", description="optimizer of the incremental mapper's BAs with fixed intrinsics (local, "
        "refinement, final; mapper_refining_optimizer for the others): each starts near its optimum, "
        "where Gauss-Newton's steps are the ones LM takes (lego, RANSAC seed 0: its 106 BAs replayed, "
        "1.56 -> 1.26 CPU s; one 4-image refinement falls back to LM).",
    )
    mapper_refining_optimizer: Literal["levenberg_marquardt", "gauss_newton"] = Field(
        "levenberg_marquardt", description="optimizer of the mapper's BAs that refine intrinsics: they start "
        "from a focal length prior, not near their optimum, where Gauss-Newton's undamped first step "
        "threw points behind the cameras (GTSAM printing a CheiralityException line for each: 186 on "
        "lego without calibration.txt) before it fell back to Levenberg-Marquardt.",
    )
    ordering: Literal["points_first", "colamd", "metis", "natural"] = Field(
        "points_first",
        description="Elimination order: points_first eliminates every point before any camera (the Schur "
        "complement, as Ceres' SCHUR solvers do); colamd/metis are GTSAM's fill-reducing heuristics.",
    )
    mapper_global_ordering: Literal["points_first", "colamd", "metis", "natural"] = Field(
        "colamd", description="elimination order of the incremental mapper's global BAs (initial pair, "
        "refinement, final; the local BAs keep `ordering`, where COLAMD was slower): on lego, RANSAC seeds "
        "0-2, the 18 global BAs took 0.53 -> 0.49 CPU s with COLAMD's order, the same iterations and models.",
    )
    mapper_refining_global_ordering: Literal["points_first", "colamd", "metis", "natural"] = Field(
        "points_first", description="elimination order of the mapper's global BAs that refine intrinsics "
        "(without calibration.txt): the calibration variable is linked to every point, and COLAMD's order "
        "made each iteration several times slower (fountain-P11 without calibration.txt: the 7 global BAs "
        "after the first two took 20.0 s with COLAMD, 3.3 s points first: the same 15 iterations and model).",
    )
    linear_solver: Literal[
        "multifrontal_cholesky", "multifrontal_qr", "sequential_cholesky", "sequential_qr", "pcg_block_jacobi"
    ] = Field(
        "sequential_cholesky",
        description="GTSAM linear solver used inside each LM step (sequential Cholesky: the same steps as "
        "multifrontal on BA problems, ~20 % less CPU on lego's local BAs). pcg_block_jacobi is GTSAM's "
        "conjugate gradient with a block-Jacobi preconditioner: its inexact steps make it ~25 % faster on "
        "large problems, but it stops ~1e-5..2e-4 above the optimal cost and cannot recover noise-free "
        "scenes to 1e-6, hence not the default.",
    )
    lambda_initial: float = Field(
        1e-3, gt=0, description="Initial Levenberg-Marquardt damping (1e-3: the same iterations and cost as "
        "1e-5 on lego's BAs, with fewer rejected steps).",
    )
    lambda_factor: float = Field(10.0, gt=1, description="Damping is multiplied/divided by this per step.")
    diagonal_damping: bool = Field(
        False, description="Damp with lambda * diag(J^T J) (Marquardt) instead of lambda * I (Levenberg)."
    )
    fixed_camera_sigma: float = Field(
        1e-6, gt=0, description="Std-dev (rad and world units) of the near-hard prior on a fixed camera."
    )
    fixed_intrinsics_sigma: float = Field(
        1e-6, gt=0, description="Std-dev (pixels or unitless) of the near-hard prior holding an intrinsic "
        "parameter that is not refined (principal point, skew, coefficients the model lacks)."
    )
    scale_sigma_relative: float = Field(
        1e-2, gt=0,
        description="Std-dev of the scale prior as a fraction of the reference distance. The pixels say "
        "nothing about scale, so a soft prior keeps the distance just as well, while a stiff one makes "
        "LM reject long steps (the distance is nonlinear in the poses).",
    )


class FilterConfig(StrictConfig):
    """Which triangulated points are kept."""

    max_reprojection_px: float = Field(4.0, gt=0, description="Drop points whose error exceeds this.")
    max_reprojection_sigmas: float = Field(
        5.0, ge=0, description="Also drop observations beyond this many standard deviations of the pixel "
        "noise measured on the model's own residuals (the smaller limit wins; 0: the fixed limit only). Far "
        "past the Gaussian tail (exp(-k^2/2): 4e-6 of true observations lost at 5): real localisation errors "
        "are heavier-tailed, and a tight limit starves the images seen by few points.",
    )
    min_reprojection_px: float = Field(
        0.5, gt=0, description="The noise-following limit never goes below this (exact measurements would "
        "give 0).",
    )
    min_triangulation_angle_deg: float = Field(
        1.5, ge=0, description="Drop points seen at smaller angles (COLMAP's filter_min_tri_angle)."
    )


class SiftConfig(StrictConfig):
    """SIFT features and matching (used when no match files are given)."""

    max_features: int = Field(8192, ge=100, description="Feature budget: most keypoints kept per image.")
    max_image_side: int = Field(
        1600, ge=64, description="Detect on the image downscaled to this longest side; keypoints mapped back "
        "to full-size pixels. OpenCV's SIFT doubles the image first (its first octave is -1), so its finest "
        "scale still samples a 3200 px photo's every pixel (COLMAP's 3200 px limit), in a third of the time: "
        "full-size fountain-P11 photos (3072x2048) keep their 8192 keypoints, in 0.65 instead of 1.8 CPU s "
        "each, with 2.6 % more verified matches (benchmarks/bench_detection.py) and a rotation error of "
        "0.027 instead of 0.031 deg (benchmarks/bench_sfm.py). Smaller images are detected at full size.",
    )
    contrast_threshold: float = Field(
        0.0236, gt=0, description="OpenCV SIFT contrastThreshold: a keypoint's interpolated DoG contrast "
        "(intensities 0..1) must reach contrast_threshold / 3. Not COLMAP's 0.02 (its peak threshold 0.02 / "
        "3): OpenCV first skips DoG samples with |D| <= floor(contrast_threshold / 3 * 0.5 * 255) (0..255 "
        "units), 0 below 0.02353, so every nonzero extremum is refined. At 0.0236 the skip is on "
        "(benchmarks/bench_detection.py): lego's 90 views detect in 1.22 instead of 1.99 CPU s with 1.3 % "
        "fewer keypoints, all found at 0.02 too (the weakest go); two full-size fountain-P11 views keep the "
        "same 8192 keypoints each, in 3.53 instead of 3.78 s.",
    )
    low_contrast: float = Field(
        0.06, ge=0, description="Low-contrast images (a dark object on a dark background): when the RMS "
        "contrast of an image's textured pixels (std of its intensities 0..1 where the 9 x 9 neighbourhood "
        "is not constant) is below this, its contrast_threshold is scaled by contrast / reference_contrast "
        "(DoG responses scale with the contrast: its structure is detected as at the reference contrast), "
        "at least min_contrast_factor, and its constant regions are masked out, so that a flat background, "
        "whose noise the lower threshold would pick up, gives no keypoints. 0: off. The benchmark photos lie "
        "above it (fountain-P11 0.10-0.17, Herz-Jesus-P8 0.17-0.19, Unity Hall 0.25, lego 0.27-0.33): "
        "unchanged.",
    )
    reference_contrast: float = Field(
        0.25, gt=0, description="The RMS contrast of a typical photo, which a low-contrast image's threshold "
        "is scaled to.",
    )
    min_contrast_factor: float = Field(
        0.2, gt=0, le=1, description="The lowest fraction of contrast_threshold a low-contrast image gets.",
    )
    constant_region_std: float = Field(
        1.0 / 255, ge=0, description="A pixel whose 9 x 9 neighbourhood has an intensity std (0..1) below "
        "this lies in a constant region (masked out in low-contrast images).",
    )
    ratio: float = Field(0.8, gt=0, lt=1, description="Lowe's ratio test threshold.")
    max_distance: float = Field(
        0.7, gt=0, description="Largest descriptor distance of a match (RootSIFT: unit norm; COLMAP's 0.7)."
    )
    exhaustive_up_to: int = Field(
        250, ge=2, description="Match all pairs up to this many images; beyond, retrieval + sequence pairs."
    )
    retrieval_neighbours: int = Field(30, ge=1, description="Most similar images (VLAD) matched per image.")
    sequential_neighbours: int = Field(
        10, ge=0, description="When the names are numbered, each image is also matched with its next ones."
    )
    vocabulary_size: int = Field(64, ge=2, description="k-means words of the VLAD vocabulary.")
    pair_selection: Literal["auto", "video"] = Field(
        "auto", description="auto: exhaustive up to exhaustive_up_to images, then retrieval + sequence; "
        "video (frames of one video, numbered in order): each frame with its sequential_neighbours next "
        "frames, plus loop_closure_neighbours retrieval pairs per frame outside that window.",
    )
    loop_closure_neighbours: int = Field(
        5, ge=0, description="pair_selection video: most similar frames (VLAD) beyond the sequential window "
        "matched per frame, so that a camera path returning to a place closes its loop.",
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Device of the descriptor matching: cpu (numpy) or cuda (torch); auto: CUDA "
        "when an NVIDIA driver is present and torch sees a GPU (torch is not imported without a driver).",
    )
    workers: int = Field(
        0, ge=0, description="Threads detecting features, then processes matching and verifying image "
        "pairs, side by side (0: one per available CPU core; 1: all in the calling process).",
    )


class TwoViewConfig(StrictConfig):
    """Geometric verification of an image pair and its two-view geometry type (COLMAP's)."""

    relative_pose: Literal["five-point", "eight-point"] = Field(
        "five-point",
        description="five-point: E by the minimal 5-point solver in RANSAC (needs K); eight-point: the "
        "seed's normalized 8-point F in RANSAC, then E = K^T F K.",
    )
    estimator: Literal["numpy", "opencv"] = Field(
        "numpy",
        description="RANSAC of F, E and H: numpy: the project's own driver (LO-RANSAC, batched minimal "
        "solvers); opencv: cv2's compiled RANSAC with the same minimal solvers, inliers re-scored by the "
        "project's residuals.",
    )
    max_error_px: float = Field(4.0, gt=0, description="Inlier threshold (Sampson / transfer error), pixels.")
    min_inliers: int = Field(15, ge=8, description="Fewest inliers of a verified pair.")
    min_e_f_inlier_ratio: float = Field(
        0.95, gt=0, le=1, description="E is trusted (calibrated) when its inliers reach this share of F's."
    )
    max_h_inlier_ratio: float = Field(
        0.8, gt=0, le=1, description="Planar or pure rotation when H explains over this share of E's inliers."
    )
    max_rotation_translation: float = Field(
        0.02, gt=0,
        description="A planar-or-panoramic pair is a pure rotation (panoramic) when the baseline over the "
        "scene plane's distance, from H's singular values, is below this.",
    )
    max_rotation_residual_deg: float | None = Field(
        90.0, gt=0, le=180,
        description="A verified pair whose relative rotation is further than this from the world rotations "
        "averaged over the view graph is a look-alike (a symmetric object's far side seen as its near side): "
        "its matches stay out of the tracks (`features.view_graph`). None: every verified pair is kept.",
    )
    anchor_pairs_per_image: int = Field(
        2, ge=1,
        description="The rotations are averaged over each image's this many pairs with the most inliers (a "
        "look-alike shares only the symmetric part of two views: fewer inliers than true neighbours).",
    )


class MapperConfig(StrictConfig):
    """The incremental mapper: initial pair, registration, triangulation, refinement, several models."""

    min_initial_pair_inliers: int = Field(
        30, ge=8, description="Fewest well-conditioned points of an initial pair."
    )
    min_initial_pair_median_angle_deg: float = Field(
        2.0, gt=0, description="An initial pair's median triangulation angle must reach this (no rotation)."
    )
    preferred_initial_pair_angle_deg: float = Field(
        8.0, gt=0, description="Of a batch's passing candidates, those reaching this median angle win."
    )
    initial_pair_max_error_px: float = Field(
        1.0, gt=0, description="Sampson threshold of the initial pair's relative pose (relative_pose "
        "five-point): E is estimated again in RANSAC on the pair's verified inliers (two_view.max_error_px, "
        "4 px, decides those) at this threshold and polished, so the pose rests on the matches that fit it "
        "tightly (kept from verification when fewer than min_initial_pair_inliers do).",
    )
    initial_pair_candidates: int = Field(
        10, ge=1, description="Passing initial-pair candidates (most shared tracks first) compared when "
        "none reaches preferred_initial_pair_angle_deg; failed ones are skipped until the graph has no pair.",
    )
    min_pnp_correspondences: int = Field(
        6, ge=6, description="Fewest 2D-3D matches to try registering an image."
    )
    min_pnp_inliers: int = Field(
        12, ge=6, description="Fewest absolute-pose inliers to accept a registration."
    )
    min_pnp_inlier_ratio: float = Field(
        0.25, gt=0, le=1, description="Fewest absolute-pose inliers as a fraction of the 2D-3D matches."
    )
    absolute_pose: Literal["p3p", "dlt"] = Field(
        "p3p", description="p3p: P3P in LO-RANSAC (EPnP local optimization); dlt: the 6-point linear PnP."
    )
    registration_turn_deg: float = Field(
        10.0, ge=0, description="Each absolute pose is also refined from starts turned by this about the "
        "camera's x and y axes; one that ends with clearly more inliers at a clearly lower cost replaces it "
        "(`pnp.consensus_from_turned_starts`, registration_turn_min_gain; 0: off). On the lego video "
        "(bench_video --seed 2) RANSAC's pose of keyframe 000176 explained 29 of 66 correspondences 9.5 deg "
        "off the truth; a start turned 10 deg found the true pose's basin with 32.",
    )
    registration_turn_min_gain: float = Field(
        0.05, ge=0, lt=1, description="A turned start replaces RANSAC's pose only with over 1 + this times "
        "its inliers at under 1 - this times its MSAC cost: most gains are a borderline inlier in the same "
        "basin at about the same cost (lego_ring_400, seeds 0 and 14: 0.1-2.5 % lower; taking them put "
        "the mean rotation error at 0.315 and 0.469 deg, not 0.275 and 0.319). Keyframe 000176 of the "
        "lego video (seed 2): 29 -> 32 inliers, 8.7 % lower.",
    )
    max_registration_trials: int = Field(
        3, ge=1, description="Failed registrations before an image is given up."
    )
    pnp_threshold_noise_factor: float = Field(
        2.0, ge=0, description="The PnP inlier threshold is at most this times the filters' noise-following "
        "reprojection limit (max_reprojection_sigmas x the measured pixel noise; 0: pnp_threshold_px "
        "only). A threshold far above the noise lets a wrong pose gather as many loose inliers as the true "
        "one: lego (mapper only, RANSAC seeds 0-9) registered r_25.png (50 correspondences, a third of them "
        "right) 12 deg off on seed 4 with a fixed 4 px (~17 sigma), 18 deg off on seed 5 with 3 px; with 2 x "
        "the limit (~2.3 px) no image is over 2.3 deg off on seeds 0-19 (1.5 and 3 x, seeds 0-9: 3.6 and "
        "4.4). "
        "Herz-Jesus-P8 pays 0.0985 -> 0.106 deg mean rotation error.",
    )
    relaxed_registration_factor: float = Field(
        0.5, gt=0, lt=1, description="When registration stalls, the inlier minimums are multiplied by this, "
        "once per model; the PnP inlier threshold stays. Dividing the threshold by it too, as before: lego "
        "end to end (bench_sfm.py --seeds 0-19) put the last two images, registered in the relaxed pass from "
        "~20 correspondences, 7-16 deg off on seeds 6, 9 and 17 (means 0.487, 0.873, 0.519 deg); with the "
        "threshold kept, every seed 0-19 has a mean <= 0.457 deg (worst image 4.7 deg, seed 10).",
    )
    triangulation_hypotheses: int = Field(
        8, ge=1, description="Two-view hypotheses per track in the RANSAC multi-view triangulation."
    )
    retriangulation_min_ratio: float = Field(
        0.2, ge=0, le=1, description="Image pairs with fewer triangulated shared tracks than this fraction "
        "are re-triangulated (COLMAP's re_min_ratio).",
    )
    local_intrinsics_until_images: int = Field(
        20, ge=2, description="Local BAs refine a shared camera's intrinsics (when the reconstruction "
        "refines them) only while the model has fewer images than this; from then on they hold them, and "
        "the global refinements (every global_ba_growth) and the final BA go on refining them (per-image "
        "cameras: every local BA refines its images' own): one more image adds "
        "little to what twenty determine, and a local BA that refines the shared camera takes "
        "local_max_iterations_refining steps with every point of its window tied to it. Without "
        "calibration (bench_sfm.py): lego_200 5.7 s instead of 7.4 s end to end (pycolmap 6.2 / 5.8 s), "
        "RANSAC seeds 0-15 at 0.596 deg mean rotation error against 0.607; lego_ring_400 (seeds 0-7) 50/50 "
        "on every seed (seed 0: 41/50 before) at 0.268 deg against 0.251.",
    )
    global_ba_growth: float = Field(
        1.25, gt=1, description="Global refinement whenever the registered images grew by this factor."
    )
    growth_refinement_rounds: int = Field(
        1, ge=1, description="Rounds of each refinement while the model grows (the local BAs that follow "
        "adjust what its filter and re-triangulation changed). 1 instead of 2 (mapper only): lego (seeds "
        "0 / 1 / 2) 0.375 / 0.366 / 0.377 deg mean rotation error against 0.380 / 0.368 / 0.366 in ~10 % "
        "less CPU; fountain-P11 0.0320 against 0.0332 deg and Herz-Jesus-P8 0.0985 against 0.1026, "
        "~12 % less.",
    )
    refinement_max_rounds: int = Field(
        2, ge=1, description="Rounds of the final refinement: BA, complete/merge, filter, retriangulate. 2 "
        "(measured when every refinement had this many): on lego (mapper only, RANSAC seeds 0 / 1 / 2) "
        "0.382 / 0.369 / 0.369 deg mean rotation error against 0.377 / 0.374 / 0.374 with 5 rounds, in "
        "10-20 % less mapping CPU (the later rounds trade the same few observations back and forth).",
    )
    refinement_min_change: float = Field(
        5e-4, ge=0, description="Refinement stops when fewer than this fraction of observations changed."
    )
    refinement_relative_error_tol: float = Field(
        1e-3, gt=0, description="Relative cost decrease at which the initial pair's BA and each refinement "
        "round's global BA stop (the local BAs and the final global BA follow). 1e-3 instead of 1e-6 "
        "(mapper only, same poses and points): lego (seeds 0 / 1 / 2) 2 LM iterations instead of 3-4 per "
        "refinement BA, ~0.25 s less CPU; fountain-P11's initial pair 3 iterations instead of 48 (the "
        "last 45 removed 0.07 % of its cost), ~1 s less CPU.",
    )
    refinement_max_iterations: int = Field(
        1, ge=1, description="Iterations of the initial pair's BA and of each refinement round's global BA "
        "with fixed intrinsics (refining them: max_iterations, as local_max_iterations_refining says why; "
        "the final global BA converges). 1: one Gauss-Newton step (on lego, seed 0, a second step removed "
        "< 0.03 % of the cost from the fourth refinement on, up to 2.8 % before); on lego's RANSAC seeds "
        "0-19 with local_max_iterations 1, instead of 100 (mapper only): every seed 90/90, mean rotation "
        "error 0.395 deg against 0.397 (mean of the seeds' means), mapper 32.7 -> 29.2 CPU s in all; "
        "fountain-P11 and Herz-Jesus-P8 as before; end to end with local_max_iterations 2, see there.",
    )
    final_relative_error_tol: float = Field(
        1e-7, gt=0, description="Relative cost decrease at which the final global BA stops (converged: "
        "Ceres, started from the result, removes < 0.001 %). 1e-7 instead of 1e-9: on lego (mapper only, "
        "seeds 0 / 1 / 2) the same poses to 0.001 deg in ~25 % less final-BA time.",
    )
    final_min_change: float = Field(
        2e-3, ge=0, description="The final global BA is run again only when its filter removed more than "
        "this fraction of the observations. 2e-3 instead of 0 (any): on lego (mapper only, seeds 0 / 1 / 2) "
        "one final BA instead of 3 / 2 / 3 (its filter removes ~0.1 %), 0.1-0.25 s less mapping CPU, "
        "mean rotation error 0.380 / 0.368 / 0.366 deg against 0.382 / 0.369 / 0.369.",
    )
    verify_min_inliers: int = Field(
        12, ge=6, description="Every registration, relaxed or not, needs this many absolute-pose inliers: "
        "relaxing min_pnp_inliers never goes below it. On lego_ring_400 (mapper only) the images registered "
        "with 6-11 inliers in the relaxed pass were the wrong ones (r_28 with 6 of 29, r_12 with 8 of 30: "
        "172-176 deg off; r_34 with 11 of 29: 6 deg off); with 12, 40/50 register, none over 0.6 deg off. "
        "COLMAP's 30 registered 29/50 there.",
    )
    verify_min_inlier_ratio: float = Field(
        0.2, gt=0, le=1, description="... and this fraction of its 2D-3D correspondences as inliers, relaxed "
        "or not (COLMAP: 25 %).",
    )
    verify_min_inlier_spread: float = Field(
        0.05, ge=0, le=1, description="Its inliers must lie in this share of the image's 8 x 8 grid cells "
        "(0.05: 4 cells): a pose resting on one small part of the image is refused.",
    )
    verify_max_rotation_std_deg: float = Field(
        3.0, gt=0, description="A registration's inliers must determine its rotation to this: one std-dev at "
        "1 px of pixel noise, from the pose's Jacobian (`verification.pose_rotation_std_deg`), a measure of "
        "their geometry (the measured noise is smaller, but the points' own errors are not in it). A looser "
        "pose is refused and tried again later, when more points may pin it. Without it, lego_ring_400 "
        "(RANSAC seed 7) registered r_88 at 4.6 deg and r_34 (13 inliers) at 4.4 deg, 8 deg off the truth, "
        "and seven later views built on them; lego's registrations (seeds 0-15) stay under 1.9 deg but "
        "one, at 3.4 deg on seed 14 (report.json: registration_rotation_std_deg).",
    )
    verify_pair_min_inliers: int = Field(
        30, ge=8, description="Verified pairs with this many inliers vote on a registered image's rotation "
        "(weaker pairs' E were often 20-50 deg off the truth on lego_ring_400).",
    )
    verify_max_rotation_deviation_deg: float = Field(
        60.0, gt=0, le=180, description="A pair agrees with a pose when the model's relative rotation is "
        "within this of its verified E's rotation. On lego_ring_400 the verified E of pairs with >= 30 "
        "inliers were within 22 deg of the true relative rotation in 90 % (median 3.9, worst 50): the "
        "vote catches far-side placements (130-180 deg there), not small errors. 30 refused lego_200's "
        "r_86 (its one voting pair 50 deg off) and left the mean rotation error at 0.437 deg, not 0.413.",
    )
    verify_min_essential_singular_ratio: float = Field(
        0.85, ge=0, le=1, description="Without calibration a pair verified only F; it votes when its "
        "E = K^T F K under the model's current intrinsics is an essential matrix: second singular value >= "
        "this times the first (1 for an exact F and the right K). Below it F disagrees with the camera (a "
        "wide, near-planar pair's F, or an unrefined focal prior) and its rotation is no evidence: on "
        "fountain-P11 under the refined focal, 0010's pairs with 0002-0004 (ratios 0.58-0.82) were 48-93 "
        "deg off the truth and refused it, while 49 of 52 pairs within 10 deg had >= 0.85.",
    )
    verify_veto_support_ratio: float = Field(
        0.5, ge=0, le=1, description="A pair whose rotation disagrees with a pose keeps its vote only when "
        "the pose's relative geometry explains less than this times the share of their track "
        "correspondences that the pair's own E explains (Sampson distance under the PnP threshold); "
        "otherwise its E is what is off, not the pose. A mirrored placement explains almost none of a true "
        "neighbour's correspondences. On the lego video (bench_video --seed 1) a 31-inlier pair's E 67 deg "
        "off vetoed a keyframe whose pose explained 61-66 % of their 38 correspondences (the true pose: "
        "61 %). 0: no pair vetoes (the vote is off).",
    )
    verify_min_rotation_agreement: float = Field(
        1.0, ge=0, le=1, description="Least share of the voting pairs' inliers that must agree with a "
        "registration's rotation (1: every voting pair, a veto); an image below it is refused (at "
        "registration) or removed (after a global refinement) and tried again later. A majority is not "
        "enough: the far-side pairs of a symmetric object's image vote for its mirrored placement, and "
        "they can outnumber its true neighbours (synthetic symmetric rings).",
    )
    guided_matching: bool = Field(
        True, description="An image whose absolute pose failed the inlier minimums on its tracks' 2D-3D "
        "correspondences is matched again against the model (`mapper.guided`): its keypoints against the "
        "descriptors of the points its failed pose projects within guided_radius_px of them (SIFT "
        "features only); the pose is estimated again from both and held to the same checks.",
    )
    guided_min_inliers: int = Field(
        4, ge=1, description="A registration with guided matches needs this many of its inliers among them: "
        "the pose then rests on evidence the failed attempt did not have, not on a second RANSAC draw over "
        "nearly the same correspondences.",
    )
    guided_radius_px: float = Field(
        8.0, gt=0, description="A keypoint is compared with the points the failed pose projects within this "
        "many pixels of it.",
    )
    final_ba_keypoint_size_px: float = Field(
        2.5, ge=0, description="In the final global BA an observation's pixel std-dev is "
        "measurement_sigma_px x max(1, its SIFT keypoint's size / this) (size: the keypoint's diameter in "
        "full-resolution pixels): a keypoint found at a coarse scale is localised less well (on lego the "
        "final residual RMS is 0.28 px at sizes under 3 px, 0.42 px from 5 px on), and a few hundred of "
        "them on one side of the object bend what the fine ones say; the final filter holds each to the "
        "limit times its std-dev (under max_reprojection_px). 0: every observation alike (match files have "
        "no sizes). Lego end to end (bench_sfm.py --seeds 0-7): mean of the seeds' mean rotation errors "
        "0.394 instead of 0.422 deg, lower on every seed, worst image 2.93 instead of 3.38 deg; mapping "
        "CPU +0.1 s (1.8 -> 1.9 s: the weighted final BA takes 4 iterations instead of 2). 2.0 and 3.5 "
        "measured within 0.01 deg of 2.5 (mapper only, two feature seeds x RANSAC seeds 0-3).",
    )
    fold_min_shared: float = Field(
        0.5, ge=0, le=1, description="report.json warns that a model may be folded onto itself when at least "
        "fold_min_pairs pairs of its cameras placed within fold_max_angle_deg of one viewpoint observe under "
        "this share of the points they should share (`verification.shared_views`): a symmetric object's "
        "look-alike sides put cameras of its far side at the near side's viewpoints. Pairs that close share "
        "0.56 or more in lego_200's and lego_ring_400's models, 0.14-0.33 in the folded models of a rendered "
        "box with look-alike opposite sides (bench_sfm.py --sets box,box24, before the look-alike pairs were "
        "left out of the tracks: `features.view_graph`). 0: no check.",
    )
    fold_max_angle_deg: float = Field(
        5.0, gt=0, description="Cameras this close (their relative rotation, and their baseline seen from "
        "their points) are at one viewpoint for the fold check.",
    )
    fold_min_pairs: int = Field(
        3, ge=1, description="Pairs at one viewpoint sharing under fold_min_shared that make a warning, "
        "and look-alike pairs that a model without calibration.txt places as their own rotation does that "
        "make it folded, when they are also half of those between its images (`view_graph.is_adopted`), and "
        "run again under its refined camera (`pipeline.fold_check`, also while it grows: "
        "`pipeline.FirstMappingProbe`): a folded model has one of each for nearly every camera of its far "
        "side (a rendered 20-view box: 19 of 27 look-alikes adopted at the end, 6 of 8 by its 9th image); "
        "one or two are poorly seen views.",
    )
    deregister_min_kept_ratio: float = Field(
        0.5, ge=0, le=1, description="After each global refinement, an image whose observations fell below "
        "this fraction of the inliers it was registered with is removed and tried again later.",
    )
    max_deregistrations: int = Field(
        1, ge=0, description="Times an image may be removed from a model before it is given up.",
    )
    merge_models: bool = Field(
        True, description="Try to move each further model into the largest one's frame (a similarity from "
        "their shared points, judged by the keypoints of each model's images that the other's points reach; "
        "see merge_min_inliers) instead of keeping it apart.",
    )
    merge_min_inliers: int = Field(
        30, ge=6, description="A merge needs this many cross-model 2D-3D correspondences (keypoints of one "
        "model's images, points of the other) within the absolute-pose threshold, merge_min_overlap, and "
        "every moved image's rotation in agreement with its verified pairs; after the merge's global "
        "refinement, a moved image that kept under deregister_min_kept_ratio of its observations is removed "
        "like any registration. No inlier ratio: on lego_ring_400 the true similarity reprojected 94 of 515 "
        "(18 %), one 25 deg off 84 (16 %).",
    )
    merge_min_overlap: float = Field(
        0.45, gt=0, le=1, description="... and this share of the moved model's points within "
        "merge_overlap_spacings of a point of the largest model. On lego_ring_400: 59 % for the true "
        "similarity, 22 % for one 25 deg off that reprojected almost as many correspondences, 49 % for one "
        "that left its 10 views within 2 deg (uncalibrated, RANSAC seed 0); on its ring of 33 views from the "
        "second (seed 1), 43 % for one from 10 shared points that left 6 views 5-11 deg off.",
    )
    merge_overlap_spacings: float = Field(
        2.0, gt=0, description="The overlap's distance, in the largest model's median distance between a "
        "point and its nearest neighbour.",
    )
    min_model_images: int = Field(3, ge=2, description="Smaller models are discarded (2 for a 2-image set).")
    max_models: int = Field(10, ge=1, description="Most models started from the images left unregistered.")
    export_all_models: bool = Field(
        False, description="Write every model (OUT/models/<k>/), not only the largest one into OUT/."
    )


class CameraConfig(StrictConfig):
    """The camera model, where its first focal length comes from, and what the bundle adjustment refines.

    With a calibration file, its K is held fixed and only the model's distortion is refined; without
    one, the focal length comes from the EXIF (else focal_prior_factor * max(width, height), with a
    warning) and the focal length and distortion are refined, and the principal point, starting at the
    image centre, is refined too for a shared camera (`refine_principal_point`). With a calibration file
    the principal point stays the calibration's.
    """

    model: Literal["auto", "pinhole", "simple-radial", "radial", "opencv"] = Field(
        "auto", description="Camera model (COLMAP's). auto: pinhole with a calibration file (K fixed, as "
        "given), simple-radial (one focal length and k1, COLMAP's default) without one."
    )
    single_camera: bool = Field(True, description="One camera shared by all images (False: one per image).")
    use_exif: bool = Field(True, description="First focal length from the photos' EXIF when present.")
    refine_principal_point: bool | None = Field(
        None, description="Refine cx, cy when there is no calibration file. None: refined for a shared "
        "camera, held at the image centre for per-image cameras (each sees too little to determine it). "
        "COLMAP holds it by default; measured here, holding it 22 px from the true one turned every "
        "Strecha camera by 0.46 deg, while the synthetic off-centre checks (bench_intrinsics.py "
        "--synthetic) recover it within 2 px."
    )
    principal_point_in_final_rounds_only: bool = Field(
        True, description="A refined principal point is held at its start while the model grows and "
        "refined from the final global refinement on (once the structure is good); False: from the first BA."
    )
    principal_point_min_d2: float = Field(
        9.21, ge=0, description="A refined principal point is kept only when its shift from the image centre "
        "is significant: delta^T Sigma^-1 delta (Sigma: its marginal covariance in the final BA at the "
        "measured noise) reaches this; else it is put back at the centre and held. 9.21: chi-square with "
        "2 degrees of freedom at 99 %. On the synthetic object ring with it centred, a free principal point "
        "cost 0.16 deg against 0.10 held (bench_intrinsics.py --synthetic). 0: always kept. Per-image "
        "cameras (principal point refined on request only) are not tested."
    )
    focal_prior_factor: float = Field(
        1.2, gt=0, description="Focal length = this * max(width, height) when neither calibration nor EXIF "
        "gives one (COLMAP's prior)."
    )
    focal_from_pairs: bool = Field(
        True, description="Without calibration file and EXIF, a shared camera starts from the focal length "
        "that makes the verified pairs' E = K^T F K most nearly essential (`calibration.self_calibration`) "
        "instead of the prior, when they determine one: the BA refines it from there instead of crawling "
        "from the prior (fountain-P11: 2655 px against the prior's 3686 and the truth's 2762; mapping 23 -> "
        "14 s). On object rings F does not determine it, and the prior stays."
    )
    focal_search_factor: float = Field(
        3.0, gt=1, description="focal_from_pairs searches [prior / this, prior * this]."
    )
    focal_min_contrast: float = Field(
        1.3, ge=1, description="focal_from_pairs keeps its minimum only when the pairs' cost 25 % away on "
        "either side is this many times higher (fountain-P11 2.19, Herz-Jesus-P8 1.64; lego rings: no "
        "minimum inside the range)."
    )
    min_field_of_view_deg: float = Field(
        2.0, gt=0, lt=180, description="EXIF focal lengths giving a narrower field of view are ignored."
    )
    max_field_of_view_deg: float = Field(
        150.0, gt=0, lt=180, description="EXIF focal lengths giving a wider field of view are ignored."
    )


class VideoConfig(StrictConfig):
    """A video as input: its frames decoded, the blurred ones dropped and keyframes chosen by how far the
    view moved since the last keyframe (`estimation.io.video`)."""

    max_side: int = Field(
        1920, ge=64, description="Keyframes are written with at most this longest side (never upscaled)."
    )
    analysis_max_side: int = Field(
        480, ge=64, description="Sharpness and optical flow are measured on frames downscaled to this side."
    )
    tracked_corners: int = Field(
        400, ge=10, description="Most corners tracked (KLT) from one frame into the next to measure motion."
    )
    blur_window: int = Field(
        15, ge=1, description="A frame's sharpness is compared with the median over this many frames on "
        "each side (half a second at 30 fps).",
    )
    blur_ratio: float = Field(
        0.6, gt=0, lt=1, description="A frame is blurred, and never a keyframe, when its sharpness (variance "
        "of the Laplacian) is below this fraction of its neighbours' median.",
    )
    keyframe_motion: float = Field(
        0.05, gt=0, description="A new keyframe once the median optical flow since the last one reaches "
        "this fraction of the image diagonal ...",
    )
    min_overlap: float = Field(
        0.7, gt=0, lt=1, description="... or once fewer than this share of the tracked corners survived "
        "since it.",
    )
    min_keyframes_per_minute: float = Field(
        100, gt=0, description="The keyframe spacing shrinks (down to min_spacing_factor of the thresholds) "
        "until the video gives at least this many keyframes per minute of footage ...",
    )
    max_keyframes_per_minute: float = Field(
        300, gt=0, description="... and grows until it gives at most this many."
    )
    min_spacing_factor: float = Field(
        0.25, gt=0, le=1, description="The spacing never shrinks below this fraction of the thresholds: a "
        "still camera gives few keyframes, not near-duplicates.",
    )
    bridge_share: float = Field(
        0.5, ge=0, le=1, description="A keyframe reached by a jump (the novelty of the step from the frame "
        "before it alone a keyframe's worth: a fast pan, a cut in the walk) keeps that frame too when it is "
        "at least this share of the spacing from the previous keyframe (0: never): the two keyframes would "
        "share little, and a view matched weakly with both registers through it.",
    )
    jpeg_quality: int = Field(
        100, ge=50, le=100, description="Quality of the keyframes written as JPEG. The frames were "
        "compressed once already (the video's codec); a second lossy pass quantizes away the fine "
        "texture SIFT localises its keypoints on. Lego's walk clip (bench_video.py, 65 keyframes of "
        "200 px, mapper RANSAC seeds 0-3): at 100 every keyframe registers at 0.38-0.48 deg mean rotation "
        "error against the truth (0.39-0.51 against the photos); at 98, 62/65 at 0.52-0.55; at 95, 65/65 "
        "at 0.51-0.68 (0.60-0.72 against the photos). The keyframes take ~1.6x the disk of quality 95.",
    )
    max_frames: int = Field(
        200_000, ge=2, description="Decoding stops with an error beyond this many frames (about 1.9 hours at "
        "30 fps), whatever the container says of its duration.",
    )


class ReconstructionConfig(StrictConfig):
    """Everything `estimation.reconstruct` needs besides the images folder."""

    features: Literal["auto", "matches", "sift"] = Field(
        "auto", description="auto: match files when the folder has them, else SIFT."
    )
    calibration: Path | None = Field(
        None, description="3x3 K file; default: calibration.txt in the folder, and without one the camera "
        "is calibrated from EXIF or a prior and refined (see CameraConfig)."
    )
    camera: CameraConfig = CameraConfig()
    ransac: RansacConfig = RansacConfig()
    bundle_adjustment: BundleAdjustmentConfig = BundleAdjustmentConfig()
    filter: FilterConfig = FilterConfig()
    sift: SiftConfig = SiftConfig()
    two_view: TwoViewConfig = TwoViewConfig()
    mapper: MapperConfig = MapperConfig()
    video: VideoConfig = VideoConfig()
    write_figures: bool = Field(True, description="Write the PNG figures into OUT/figures.")
