"""depths.npz: round trip, bad fields refused by name; sigma along a ray of a known covariance."""

import numpy as np
import pytest

from estimation.bundle_adjustment.factor_graph import along_ray_sigmas
from estimation.errors import InputError
from estimation.io.export import DepthObservations, read_depths, write_depths


def depths(**changes):
    fields = {"file_paths": ["images/a.jpg", "images/b.jpg"], "frame": np.array([0, 1, 1]),
              "point": np.array([[0.0, 0, 5], [1, 0, 5], [0, 1, 4]]), "sigma": np.array([0.1, 0.2, 0.05]),
              "pixel_sigma": 0.4}
    return {**fields, **changes}


def test_a_depths_file_round_trips(tmp_path):
    path = tmp_path / "depths.npz"
    write_depths(path, DepthObservations(**depths()))
    read = read_depths(path)
    assert read.file_paths == ["images/a.jpg", "images/b.jpg"] and read.pixel_sigma == 0.4
    np.testing.assert_array_equal(read.frame, [0, 1, 1])
    np.testing.assert_array_equal(read.point, depths()["point"])
    np.testing.assert_array_equal(read.sigma, depths()["sigma"])


@pytest.mark.parametrize(("change", "message"), [
    ({"sigma": np.array([0.1, np.nan, 0.05])}, "field 'sigma' has non-finite values"),
    ({"sigma": np.array([0.1, -0.2, 0.05])}, "field 'sigma' must be positive"),
    ({"point": np.array([[0.0, 0, 5], [1, 0, np.inf], [0, 1, 4]])}, "field 'point' has non-finite"),
    ({"point": np.zeros((3, 2))}, r"field 'point' must be \(O, 3\) floats"),
    ({"frame": np.array([0, 1, 2])}, "field 'frame' refers to frames outside 0..1"),
    ({"pixel_sigma": 0.0}, "field 'pixel_sigma' must be positive"),
])
def test_bad_depths_are_refused_naming_the_file_and_field(tmp_path, change, message):
    path = tmp_path / "depths.npz"
    np.savez(path, **depths(**change))
    with pytest.raises(InputError, match=f"depths.npz: {message}"):
        read_depths(path)


def test_a_depths_file_without_a_field_is_refused_naming_it(tmp_path):
    path = tmp_path / "depths.npz"
    np.savez(path, **{k: v for k, v in depths().items() if k != "sigma"})
    with pytest.raises(InputError, match="depths.npz: missing field 'sigma'"):
        read_depths(path)


def test_sigma_along_the_ray_is_the_covariance_projected_on_the_unit_ray():
    # A covariance with 0.3^2 along x and 0.1^2 along y and z: the ray along x sees 0.3, along y 0.1, and
    # the diagonal ray in the x-y plane sqrt((0.09 + 0.01) / 2).
    covariance = np.diag([0.09, 0.01, 0.01])
    centres = np.array([[-4.0, 0, 0], [0, -2, 0], [-1, -1, 0]])
    points = np.zeros((3, 3))
    sigmas = along_ray_sigmas(points, centres, np.repeat(covariance[None], 3, axis=0))
    np.testing.assert_allclose(sigmas, [0.3, 0.1, np.sqrt(0.05)])
