"""Each loader reads its format into one Dataset; bad input fails with an error naming the file or field."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from estimation.io.export import DepthObservations, transforms_dict, write_depths, write_ply
from estimation.synthetic import make_scene, project
from estimation.types import CameraPose
from neural.data import ImageSize, load_dataset
from neural.errors import DatasetError
from neural.rays import pixel_rays

LEGO_FOCAL_200 = 0.5 * 200 / math.tan(0.5 * 0.6911112070083618)


def test_blender_folder_loads_all_splits_composited_on_white(shared_data):
    dataset = load_dataset(shared_data / "lego_200")
    assert dataset.images.shape == (90, 200, 200, 3) and dataset.images.dtype == np.float32
    assert len(dataset.split("train")) == 80 and len(dataset.split("val")) == 10
    assert dataset.fx == pytest.approx(LEGO_FOCAL_200) and dataset.fy == dataset.fx
    assert (dataset.cx, dataset.cy) == (100.0, 100.0)
    assert (dataset.near, dataset.far) == (2.0, 6.0)
    assert dataset.image_names[80] == "./val/r_4"
    np.testing.assert_allclose(dataset.images[:, 0, 0], 1.0)  # corners are background
    expected_pose = json.loads((shared_data / "lego_200/transforms_train.json").read_text())["frames"][0]
    np.testing.assert_allclose(dataset.poses[0], expected_pose["transform_matrix"], atol=1e-6)


def test_blender_black_background_differs_only_where_transparent(shared_data):
    white = load_dataset(shared_data / "lego_200").images[0]
    black = load_dataset(shared_data / "lego_200", white_background=False).images[0]
    alpha = Image.open(shared_data / "lego_200/train/r_0.png").getchannel("A")
    transparency = 1.0 - np.asarray(alpha, np.float32) / 255.0
    np.testing.assert_allclose(white - black, np.repeat(transparency[..., None], 3, -1), atol=1e-6)


def test_tiny_npz_uses_its_split_and_focal(shared_data):
    dataset = load_dataset(shared_data / "lego_tiny.npz")
    assert dataset.images.shape == (90, 100, 100, 3)
    assert list(dataset.split("val")) == list(range(80, 90))
    assert dataset.fx == pytest.approx(138.888879, rel=1e-6)
    with pytest.raises(DatasetError, match="split 'test' is empty or missing"):
        dataset.split("test")


def test_npz_without_split_holds_out_every_tenth_image(tmp_path, shared_data):
    source = np.load(shared_data / "lego_tiny.npz")
    np.savez(
        tmp_path / "nosplit.npz",
        images=source["images"][:20],
        poses=source["poses"][:20],
        focal=source["focal"],
    )
    dataset = load_dataset(tmp_path / "nosplit.npz")
    assert list(dataset.split("val")) == [9, 19]
    assert len(dataset.split("train")) == 18


def write_reconstruction(folder: Path, binary_ply: bool = True, offset=(10.0, -5.0, 3.0), scale=7.0):
    """A folder laid out like `sfmnerf reconstruct` output, written with the SfM exporter's own writers."""
    scene = make_scene(num_cameras=5, num_points=300, seed=1, width=80, height=60)
    # move the scene away from the origin and scale it, so normalization has work to do
    offset = np.asarray(offset)
    points = scene.points * scale + offset
    poses = [CameraPose.from_center(pose.R, pose.center * scale + offset) for pose in scene.poses]
    (folder / "images").mkdir(parents=True)
    frames = []
    for index, pose in enumerate(poses):
        name = f"images/{index + 1}.png"
        Image.fromarray(np.full((60, 80, 3), 40 * index, np.uint8)).save(folder / name)
        frames.append((name, pose))
    (folder / "transforms.json").write_text(
        json.dumps(transforms_dict(scene.K, 80, 60, frames, "points.ply"))
    )
    write_ply(folder / "points.ply", points, scene.colors, binary=binary_ply)
    return scene, poses, points


@pytest.mark.parametrize("binary_ply", [True, False])
def test_reconstruction_folder_is_normalized_and_rays_hit_the_sparse_points(tmp_path, binary_ply):
    scene, poses, points = write_reconstruction(tmp_path, binary_ply)
    dataset = load_dataset(tmp_path)
    assert dataset.images.shape == (5, 60, 80, 3)
    assert list(dataset.split("val")) == [0] and list(dataset.split("train")) == [1, 2, 3, 4]  # LLFF
    normalized = dataset.normalization.points_to_scene(points)
    inside = np.all(
        (normalized >= dataset.scene.scene_box_min) & (normalized <= dataset.scene.scene_box_max), 1
    )
    assert inside.mean() > 0.95 and np.abs(normalized).max() < 1.5
    # the ray through a point's pixel (OpenCV pixel convention of the SfM code) passes through that point
    for index, pose in enumerate(poses):
        uv = project(scene.K, pose, points)
        c2w = torch.as_tensor(dataset.poses[index], dtype=torch.float64)
        u, v = torch.as_tensor(uv[:, 0]), torch.as_tensor(uv[:, 1])
        rays = pixel_rays(c2w, u, v, dataset.fx, dataset.fy, dataset.cx, dataset.cy)
        origins, directions = rays.origins.numpy(), rays.directions.numpy()
        to_point = normalized - origins
        distance_along = np.sum(to_point * directions, axis=1)
        miss = np.linalg.norm(to_point - distance_along[:, None] * directions, axis=1)
        assert miss.max() < 1e-3 * np.abs(normalized).max()
        assert np.all(distance_along > dataset.near) and np.all(distance_along < dataset.far)
    # poses map back to the original frame
    np.testing.assert_allclose(dataset.normalization.pose_to_original(dataset.poses)[:, :3, 3],
                               [pose.center for pose in poses], atol=1e-4)  # fmt: skip


def test_reconstruction_reads_colmap_points_when_there_is_no_ply(tmp_path):
    _, _, points = write_reconstruction(tmp_path)
    (tmp_path / "points.ply").unlink()
    (tmp_path / "sparse").mkdir()
    lines = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"]
    lines += [f"{i + 1} {x} {y} {z} 1 2 3 0.5 1 0 2 0" for i, (x, y, z) in enumerate(points)]
    (tmp_path / "sparse/points3D.txt").write_text("\n".join(lines) + "\n")
    dataset = load_dataset(tmp_path)
    assert np.abs(dataset.normalization.points_to_scene(points)).max() < 1.5


# ---------------------------------------------------------------------------------------------- errors


@pytest.fixture
def small_blender(tmp_path, shared_data) -> Path:
    """lego_200 reduced to two train and one val view, for corrupting."""
    folder = tmp_path / "blender"
    for split, keep in (("train", 2), ("val", 1)):
        meta = json.loads((shared_data / f"lego_200/transforms_{split}.json").read_text())
        meta["frames"] = meta["frames"][:keep]
        (folder / split).mkdir(parents=True)
        for frame in meta["frames"]:
            shutil.copy(shared_data / "lego_200" / (frame["file_path"] + ".png"), folder / split)
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta))
    return folder


def edit_json(path: Path, change) -> None:
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_small_blender_fixture_is_valid(small_blender):
    assert load_dataset(small_blender).images.shape == (3, 200, 200, 3)


def test_missing_image_names_the_file(small_blender):
    (small_blender / "train/r_0.png").unlink()
    with pytest.raises(DatasetError, match=r"train/r_0\.png: image file not found"):
        load_dataset(small_blender)


def test_missing_key_names_the_frame_and_key(small_blender):
    edit_json(small_blender / "transforms_val.json", lambda m: m["frames"][0].pop("transform_matrix"))
    with pytest.raises(
        DatasetError, match=r"transforms_val\.json frames\[0\]: missing key 'transform_matrix'"
    ):
        load_dataset(small_blender)
    edit_json(small_blender / "transforms_train.json", lambda m: m.pop("camera_angle_x"))
    with pytest.raises(DatasetError, match="camera_angle_x"):
        load_dataset(small_blender)


def test_non_rigid_pose_is_rejected(small_blender):
    def scale_rotation(meta):
        matrix = np.array(meta["frames"][1]["transform_matrix"])
        matrix[:3, :3] *= 1.5
        meta["frames"][1]["transform_matrix"] = matrix.tolist()

    edit_json(small_blender / "transforms_train.json", scale_rotation)
    with pytest.raises(DatasetError, match=r"frames\[1\] \(\./train/r_1\): transform_matrix is not a rigid"):
        load_dataset(small_blender)


def test_mixed_image_sizes_are_rejected(small_blender):
    image = Image.open(small_blender / "val/r_4.png")
    image.resize((100, 100)).save(small_blender / "val/r_4.png")
    with pytest.raises(DatasetError, match=r"val/r_4: image size 100x100 differs from 200x200"):
        load_dataset(small_blender)


def test_empty_split_is_rejected(small_blender):
    edit_json(small_blender / "transforms_val.json", lambda m: m.update(frames=[]))
    with pytest.raises(DatasetError, match=r"transforms_val\.json: 'frames' is empty"):
        load_dataset(small_blender)


@pytest.mark.parametrize("outside", ["existing", "missing"])
@pytest.mark.parametrize(
    "file_path",
    ["../secret/photo", "{absolute}/photo", "./train/../../secret/photo"],
    ids=["dotdot", "absolute", "nested"],
)
def test_a_frame_pointing_outside_the_dataset_is_refused_the_same_way_whether_it_exists(
    small_blender, file_path, outside
):
    secret = small_blender.parent / "secret"
    secret.mkdir()
    if outside == "existing":
        shutil.copy(small_blender / "train/r_0.png", secret / "photo.png")
    file_path = file_path.format(absolute=secret)
    edit_json(small_blender / "transforms_train.json", lambda m: m["frames"][1].update(file_path=file_path))
    with pytest.raises(DatasetError) as refused:
        load_dataset(small_blender)
    assert str(refused.value) == (
        f"{small_blender / 'transforms_train.json'} frames[1]: file_path {file_path!r} "
        "points outside the dataset folder; refused"
    )


def test_a_link_out_of_the_dataset_is_refused(small_blender, tmp_path):
    (tmp_path / "elsewhere.png").write_bytes((small_blender / "train/r_1.png").read_bytes())
    (small_blender / "train/r_1.png").unlink()
    (small_blender / "train/r_1.png").symlink_to(tmp_path / "elsewhere.png")
    with pytest.raises(DatasetError, match=r"frames\[1\]: file_path '\./train/r_1\.png' points outside"):
        load_dataset(small_blender)


def test_a_reconstruction_frame_outside_the_given_bound_is_refused(tmp_path):
    """A local reconstruction may name images anywhere; with `within` (the service) they must stay inside."""
    write_reconstruction(tmp_path / "job" / "output")
    (tmp_path / "other.png").write_bytes((tmp_path / "job/output/images/3.png").read_bytes())
    edit_json(
        tmp_path / "job/output/transforms.json", lambda m: m["frames"][2].update(file_path="../../other.png")
    )
    assert load_dataset(tmp_path / "job/output").images.shape[0] == 5
    with pytest.raises(DatasetError, match=r"frames\[2\]: file_path '\.\./\.\./other\.png' points outside"):
        load_dataset(tmp_path / "job/output", within=tmp_path / "job")


def test_npz_missing_array_and_unknown_paths(tmp_path):
    np.savez(tmp_path / "bad.npz", images=np.zeros((2, 4, 4, 3)), poses=np.tile(np.eye(4), (2, 1, 1)))
    with pytest.raises(DatasetError, match=r"bad\.npz: missing array 'focal'"):
        load_dataset(tmp_path / "bad.npz")
    with pytest.raises(DatasetError, match="no such file"):
        load_dataset(tmp_path / "nothing")
    with pytest.raises(DatasetError, match="not a dataset folder"):
        load_dataset(tmp_path)


def test_reconstruction_image_of_wrong_size_and_missing_points(tmp_path):
    write_reconstruction(tmp_path)
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "images/3.png")
    with pytest.raises(DatasetError, match=r"images/3\.png: image size 40x30 differs from w x h = 80x60"):
        load_dataset(tmp_path)
    Image.fromarray(np.zeros((60, 80, 3), np.uint8)).save(tmp_path / "images/3.png")
    (tmp_path / "points.ply").unlink()
    with pytest.raises(DatasetError, match=r"no points\.ply or sparse/points3D\.txt"):
        load_dataset(tmp_path)


# -------------------------------------------------------------------------------- images at a smaller size
def test_downscaled_loading_keeps_the_intrinsics_consistent_with_the_image(tmp_path):
    """A white dot drawn where a known 3D point projects at full size is found where the scaled intrinsics
    project it at the reduced size (also for an aspect that does not divide evenly)."""
    from neural.data import ImageSize

    scene, poses, points = write_reconstruction(tmp_path)
    full = load_dataset(tmp_path)
    index, point = 2, np.array([0.05, -0.1, 0.02])  # near the scene's centre, in the normalized frame

    def project(dataset):
        c2w = dataset.poses[index].astype(np.float64)
        camera = c2w[:3, :3].T @ (point - c2w[:3, 3])  # OpenGL camera axes: looks down -z, y up
        u = dataset.fx * camera[0] / -camera[2] + dataset.cx  # continuous pixel coordinates
        v = dataset.fy * -camera[1] / -camera[2] + dataset.cy
        return np.array([u, v])

    u, v = project(full)
    image = np.zeros((60, 80, 3), np.uint8)
    rows, cols = np.mgrid[0:60, 0:80] + 0.5
    image[(np.abs(cols - u) < 2.0) & (np.abs(rows - v) < 2.0)] = 255  # a 4x4 px dot centred on (u, v)
    Image.fromarray(image).save(tmp_path / "images/3.png")

    for size in (ImageSize(downscale=2), ImageSize(max_side=50)):
        small = load_dataset(tmp_path, image_size=size)
        width, height = size.target(80, 60)
        assert small.images.shape == (5, height, width, 3)
        assert (small.fx, small.cx) == pytest.approx((full.fx * width / 80, full.cx * width / 80))
        assert (small.fy, small.cy) == pytest.approx((full.fy * height / 60, full.cy * height / 60))
        brightness = small.images[index].mean(axis=-1)
        rows, cols = np.mgrid[0:height, 0:width] + 0.5
        centroid = np.array([(cols * brightness).sum(), (rows * brightness).sum()]) / brightness.sum()
        np.testing.assert_allclose(centroid, project(small), atol=0.1)
        np.testing.assert_allclose(project(small), [u * width / 80, v * height / 60], atol=1e-6)


def test_resized_images_are_cached_by_content_and_give_the_same_values(tmp_path):
    from neural.data import ImageSize

    write_reconstruction(tmp_path / "sfm")
    cache = tmp_path / "cache"
    first = load_dataset(tmp_path / "sfm", image_size=ImageSize(max_side=40), cache_dir=cache)
    cached_files = sorted(cache.glob("*.npy"))
    assert len(cached_files) == 5
    again = load_dataset(tmp_path / "sfm", image_size=ImageSize(max_side=40), cache_dir=cache)
    np.testing.assert_array_equal(first.images, again.images)
    uncached = load_dataset(tmp_path / "sfm", image_size=ImageSize(max_side=40))
    np.testing.assert_array_equal(first.images, uncached.images)
    # a changed photo is decoded afresh (its cache key follows the file)
    Image.fromarray(np.full((60, 80, 3), 200, np.uint8)).save(tmp_path / "sfm/images/1.png")
    changed = load_dataset(tmp_path / "sfm", image_size=ImageSize(max_side=40), cache_dir=cache)
    assert len(list(cache.glob("*.npy"))) == 6
    np.testing.assert_allclose(changed.images[0], 200 / 255, atol=1e-3)


def test_blender_and_npz_scale_their_focal_with_the_image(shared_data):
    from neural.data import ImageSize

    blender = load_dataset(shared_data / "lego_200", image_size=ImageSize(max_side=50))
    assert blender.images.shape[1:3] == (50, 50) and blender.fx == pytest.approx(LEGO_FOCAL_200 / 4)
    assert (blender.cx, blender.cy) == (25.0, 25.0)
    npz = load_dataset(shared_data / "lego_tiny.npz", image_size=ImageSize(downscale=4))
    assert npz.images.shape[1:3] == (25, 25) and npz.fx == pytest.approx(138.888879 / 4, rel=1e-6)


# ---------------------------------------------------------------------------------------- unbounded scenes
def test_unbounded_scene_holds_every_camera_in_its_box_and_reaches_far(tmp_path):
    write_reconstruction(tmp_path)
    bounded = load_dataset(tmp_path)
    unbounded = load_dataset(tmp_path, unbounded=True)
    assert not bounded.scene.unbounded and unbounded.scene.unbounded
    centres = unbounded.poses[:, :3, 3]
    assert (centres >= np.array(unbounded.scene.scene_box_min) - 1e-6).all()
    assert (centres <= np.array(unbounded.scene.scene_box_max) + 1e-6).all()
    assert unbounded.scene.far > 100 * bounded.scene.far and unbounded.near == bounded.near
    np.testing.assert_array_equal(unbounded.images, bounded.images)


# -------------------------------------------------------------------------------- lens distortion
def ray_pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour as a function of a ray's normalized direction (x, y, 1): what any camera sees."""
    red, green, blue = 0.5 + 0.4 * np.sin(9 * x), 0.5 + 0.4 * np.cos(7 * y), 0.5 + 0.3 * np.sin(5 * (x + y))
    return np.stack([red, green, blue], -1)


@pytest.mark.parametrize("distortion", [{"k1": -0.12, "k2": 0.02}, {"k1": 0.08, "p1": 0.004, "p2": -0.003}])
def test_distorted_photos_load_as_pinhole_images_of_the_same_rays(tmp_path, distortion):
    """Each photo is drawn through a distorted lens (one with its own principal point); the loaded images
    show, at every pixel, the colour of the pinhole ray the dataset's K gives that pixel."""
    from estimation.geometry.projection import Camera, pixel_to_normalized

    write_reconstruction(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta.update(distortion)
    meta["frames"][3].update(cx=meta["cx"] + 3.0, cy=meta["cy"] - 2.0)  # per-image intrinsics
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    rows, cols = np.mgrid[0:60, 0:80].astype(float)
    for frame in meta["frames"]:
        fields = {**meta, **frame}
        lens = Camera("opencv", fx=fields["fl_x"], fy=fields["fl_y"], cx=fields["cx"] - 0.5,
                      cy=fields["cy"] - 0.5, **distortion)  # fmt: skip
        x = pixel_to_normalized(lens, np.stack([cols.ravel(), rows.ravel()], -1))
        photo = ray_pattern(x[:, 0], x[:, 1]).reshape(60, 80, 3)
        Image.fromarray(np.round(photo * 255).astype(np.uint8)).save(tmp_path / frame["file_path"])

    dataset = load_dataset(tmp_path)
    x = (cols + 0.5 - dataset.cx) / dataset.fx  # the pinhole ray of each pixel (nerfstudio convention)
    y = (rows + 0.5 - dataset.cy) / dataset.fy
    for image in dataset.images:
        error = np.abs(image - ray_pattern(x, y))
        assert np.median(error) < 0.01 and error.max() < 0.06
    assert dataset.fx >= meta["fl_x"]  # zoomed in (if at all) so no pixel looks outside a photo


def test_a_camera_model_the_loader_cannot_undistort_is_refused_naming_it(tmp_path):
    write_reconstruction(tmp_path)
    edit_json(tmp_path / "transforms.json", lambda meta: meta.update(camera_model="OPENCV_FISHEYE"))
    with pytest.raises(DatasetError, match="transforms.json: camera_model 'OPENCV_FISHEYE' is not supported"):
        load_dataset(tmp_path)
    edit_json(tmp_path / "transforms.json", lambda meta: meta.update(camera_model="OPENCV", k3=0.1))
    with pytest.raises(DatasetError, match="distortion term k3"):
        load_dataset(tmp_path)


def write_depths_of(folder: Path, poses, points, sigma=0.05, file_paths=None):
    """depths.npz of every point seen by every frame, as `sfmnerf reconstruct` writes it."""
    frames = json.loads((folder / "transforms.json").read_text())["frames"]
    frame = np.repeat(np.arange(len(poses)), len(points))
    write_depths(folder / "depths.npz", DepthObservations(
        file_paths or [f["file_path"] for f in frames], frame, np.tile(points, (len(poses), 1)),
        np.full(len(frame), sigma), 0.5,
    ))  # fmt: skip


def test_depth_rays_pass_through_their_points_at_their_distance(tmp_path):
    scene, poses, points = write_reconstruction(tmp_path)
    write_depths_of(tmp_path, poses, points, sigma=0.07)
    dataset = load_dataset(tmp_path, image_size=ImageSize(max_side=40))
    depth = dataset.depth_rays
    assert depth is not None and len(depth.image) > 0.9 * len(poses) * len(points)
    c2w = torch.as_tensor(dataset.poses[depth.image], dtype=torch.float64)
    rays = pixel_rays(c2w, torch.as_tensor(depth.u), torch.as_tensor(depth.v), dataset.fx, dataset.fy,
                      dataset.cx, dataset.cy)  # fmt: skip
    ends = (rays.origins + rays.directions * torch.as_tensor(depth.distance)[:, None]).numpy()
    # each ray ends on a sparse point (float32 poses: to a millionth of the scene)
    normalized = dataset.normalization.points_to_scene(points)
    miss = np.linalg.norm(ends[:, None] - normalized[None], axis=2).min(axis=1)
    assert miss.max() < 1e-5
    np.testing.assert_allclose(depth.sigma, 0.07 * dataset.normalization.scale)
    train = depth.of_images(dataset.split("train"))
    assert set(train.image.tolist()) == {0, 1, 2, 3} and len(train.image) < len(depth.image)


def test_a_depths_file_of_other_frames_or_with_bad_values_is_refused_naming_it(tmp_path):
    scene, poses, points = write_reconstruction(tmp_path)
    names = [f"images/{index + 1}.png" for index in range(5)]
    write_depths_of(tmp_path, poses, points, file_paths=[*names[:4], "images/other.png"])
    with pytest.raises(DatasetError, match=r"depths\.npz: field 'file_paths'\[4\] is 'images/other\.png'"):
        load_dataset(tmp_path)
    write_depths_of(tmp_path, poses[:4], points, file_paths=names[:4])
    with pytest.raises(DatasetError, match=r"depths\.npz: field 'file_paths' lists 4 frames"):
        load_dataset(tmp_path)
    write_depths_of(tmp_path, poses, points, sigma=-1.0)
    with pytest.raises(DatasetError, match=r"depths\.npz: field 'sigma' must be positive"):
        load_dataset(tmp_path)
    (tmp_path / "depths.npz").unlink()
    assert load_dataset(tmp_path).depth_rays is None
