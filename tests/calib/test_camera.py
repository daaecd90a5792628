import cv2
import numpy as np
import pytest
from calib_testing import subject_points

from calib.camera import Camera, Rig
from calib.errors import InputError

REALISTIC_DIST = (-0.2, 0.05, 0.0, 0.0, 0.0)


def image_grid(camera: Camera, step: int = 16) -> np.ndarray:
    """(N, 2) pixel centres over the whole image, corners included."""
    width, height = camera.size
    u = np.append(np.arange(0, width, step), width - 1)
    v = np.append(np.arange(0, height, step), height - 1)
    return np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2).astype(np.float64)


def front_camera(dist=REALISTIC_DIST, size=(1280, 720)) -> Camera:
    return Camera.look_at("front", (0.0, -4.0, 1.5), (0.0, 0.0, 1.0), f_px=1000.0, size=size, dist=dist)


def test_project_agrees_with_cv2_project_points(rig12):
    X = subject_points(500)
    for camera in rig12:
        rvec, _ = cv2.Rodrigues(camera.R)
        expected, _ = cv2.projectPoints(X, rvec, camera.t, camera.K, camera.dist)
        np.testing.assert_allclose(camera.project(X), expected.reshape(-1, 2), rtol=0, atol=1e-6)


def test_project_all_distortion_terms_agree_with_cv2():
    camera = Camera("c", np.diag([900.0, 950.0, 1.0]) + [[0, 0, 300], [0, 0, 200], [0, 0, 0]],
                    (-0.3, 0.12, 2e-3, -1.5e-3, -0.04), np.eye(3), (0.1, -0.2, 3.0), (640, 480))
    X = np.random.default_rng(3).uniform([-1.5, -1.2, -0.5], [1.5, 1.2, 0.5], (300, 3))
    expected, _ = cv2.projectPoints(X, np.zeros(3), camera.t, camera.K, camera.dist)
    np.testing.assert_allclose(camera.project(X), expected.reshape(-1, 2), rtol=0, atol=1e-6)


def test_undistort_round_trip_over_whole_image():
    camera = front_camera()
    uv = image_grid(camera)
    rays = camera.pixel_rays(uv)
    reprojected = camera.project(camera.centre + 2.5 * rays)
    error = np.max(np.linalg.norm(reprojected - uv, axis=1))
    assert error < 1e-6, f"max round-trip error {error:.3g} px"


def test_undistort_pixels_inverts_distortion_of_normalised_coordinates():
    camera = front_camera()
    uv = image_grid(camera, step=64)
    normalised = camera.undistort_pixels(uv)
    X_cam = np.column_stack([normalised, np.ones(len(uv))])
    X = (X_cam - camera.t) @ camera.R
    np.testing.assert_allclose(camera.project(X), uv, rtol=0, atol=1e-6)


def test_pixel_derivative_is_the_projections_derivative_with_every_distortion_term_and_skew():
    camera = Camera("c", np.array([[900.0, 7.0, 300.0], [0.0, 950.0, 200.0], [0.0, 0.0, 1.0]]),
                    (-0.3, 0.12, 2e-3, -1.5e-3, -0.04), np.eye(3), (0.0, 0.0, 0.0), (640, 480))
    xy = np.random.default_rng(5).uniform(-0.4, 0.4, (50, 2))
    step = 1e-6

    def pixels(points):
        return camera.project(np.column_stack([points, np.ones(len(points))]))

    numeric = np.stack([(pixels(xy + step * e) - pixels(xy - step * e)) / (2 * step) for e in np.eye(2)], axis=2)
    np.testing.assert_allclose(camera.pixel_derivative(xy), numeric, rtol=1e-6, atol=1e-4)


def skewed_camera(skew: float = 9.0) -> Camera:
    """``front_camera`` with skew ``K[0, 1]`` pixels (real decomposed projection matrices: -0.5 to +1 px)."""
    camera = front_camera()
    K = camera.K.copy()
    K[0, 1] = skew
    return Camera(camera.name, K, camera.dist, camera.R, camera.t, camera.size)


def test_skewed_camera_round_trips_pixel_ray_pixel():
    camera = skewed_camera()
    uv = image_grid(camera)
    reprojected = camera.project(camera.centre + 2.5 * camera.pixel_rays(uv))
    error = np.max(np.linalg.norm(reprojected - uv, axis=1))
    assert error < 1e-6, f"max round-trip error {error:.3g} px"
    np.testing.assert_allclose(camera.project(camera.backproject(uv, np.full(len(uv), 3.0))), uv, atol=1e-6)


def test_skewed_projection_matches_the_hand_computed_one():
    # Identity pose, no distortion: x_img ~ K x, so (x, y, z) = (0.2, -0.1, 2) is
    # u = fx 0.1 + s (-0.05) + cx, v = fy (-0.05) + cy.
    K = np.array([[800.0, 12.0, 320.0], [0.0, 780.0, 240.0], [0.0, 0.0, 1.0]])
    camera = Camera("c", K, np.zeros(5), np.eye(3), np.zeros(3), (640, 480))
    expected = [[800.0 * 0.1 + 12.0 * -0.05 + 320.0, 780.0 * -0.05 + 240.0]]
    np.testing.assert_allclose(camera.project([[0.2, -0.1, 2.0]]), expected, rtol=0, atol=1e-12)
    # With distortion the skew acts on the distorted coordinates (u = fx x_d + s y_d + cx).
    dist = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01])
    distorted = Camera("c", K, dist, np.eye(3), np.zeros(3), (640, 480))
    plain, _ = cv2.projectPoints(np.array([[0.2, -0.1, 2.0]]), np.zeros(3), np.zeros(3), np.eye(3), dist)
    x_d, y_d = plain.reshape(2)
    np.testing.assert_allclose(distorted.project([[0.2, -0.1, 2.0]]),
                               [[800.0 * x_d + 12.0 * y_d + 320.0, 780.0 * y_d + 240.0]], rtol=0, atol=1e-9)


def test_skewed_projection_matrix_agrees_with_project():
    camera = Camera("c", skewed_camera().K, np.zeros(5), front_camera().R, front_camera().t, (1280, 720))
    X = subject_points(20)
    homogeneous = np.column_stack([X, np.ones(len(X))]) @ camera.P.T
    np.testing.assert_allclose(homogeneous[:, :2] / homogeneous[:, 2:], camera.project(X), atol=1e-9)


def test_backproject_then_project_and_depth_round_trip(rig12):
    for camera in rig12:
        uv = image_grid(camera, step=97)
        depth = np.linspace(0.5, 8.0, len(uv))
        X = camera.backproject(uv, depth)
        np.testing.assert_allclose(camera.project(X), uv, rtol=0, atol=1e-6)
        np.testing.assert_allclose(camera.depth(X), depth, rtol=0, atol=1e-12)


def test_pixel_rays_are_unit_and_pass_through_the_seen_point():
    camera = front_camera()
    X = subject_points(50)
    rays = camera.pixel_rays(camera.project(X))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    expected = (X - camera.centre) / np.linalg.norm(X - camera.centre, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, expected, atol=1e-9)


def test_look_at_puts_target_at_principal_point_and_up_upwards():
    target = np.array([0.3, -0.2, 1.1])
    camera = Camera.look_at("c", (3.0, 2.0, 2.5), target, f_px=800.0, size=(641, 481))
    np.testing.assert_allclose(camera.project(target[None]), [[320.0, 240.0]], atol=1e-9)
    above = camera.project((target + [0.0, 0.0, 0.5])[None])
    assert above[0, 1] < 240.0
    np.testing.assert_allclose(camera.centre, [3.0, 2.0, 2.5], atol=1e-12)
    assert camera.depth(target[None])[0] == pytest.approx(np.linalg.norm(target - [3.0, 2.0, 2.5]))


def test_centre_and_projection_matrix_agree_with_project():
    camera = front_camera(dist=np.zeros(5))
    X = subject_points(20)
    homogeneous = np.column_stack([X, np.ones(len(X))]) @ camera.P.T
    np.testing.assert_allclose(homogeneous[:, :2] / homogeneous[:, 2:], camera.project(X), atol=1e-9)
    np.testing.assert_allclose(camera.depth(camera.centre[None]), [0.0], atol=1e-12)


def test_in_image_uses_pixel_centre_convention():
    camera = front_camera(size=(4, 3))
    uv = np.array([[-0.5, -0.5], [3.49, 2.49], [-0.51, 0.0], [3.5, 0.0], [0.0, 2.5]])
    np.testing.assert_array_equal(camera.in_image(uv), [True, True, False, False, False])


def test_sees_keeps_points_in_front_whose_pinhole_image_is_in_the_image():
    # Strong barrel distortion folds the far field back into the image: project() puts a point 60° off
    # the axis inside it, while the point is far out of view.
    camera = Camera.look_at("c", (0.0, -3.0, 1.0), (0.0, 0.0, 1.0), f_px=500.0, size=(640, 480),
                            dist=np.array([-0.4, 0.0, 0.0, 0.0, 0.0]))
    ahead, behind = np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, -6.0, 1.0]])
    far_off_axis = np.array([[3.0 * np.tan(np.radians(60.0)), 0.0, 1.0]])
    assert camera.in_image(camera.project(far_off_axis))[0]
    np.testing.assert_array_equal(camera.sees(np.vstack([ahead, behind, far_off_axis])), [True, False, False])
    assert camera.sees(np.zeros((0, 3))).shape == (0,)


def test_arrays_are_read_only_float64_copies():
    R = np.eye(3)
    camera = Camera("c", np.diag([500.0, 500.0, 1.0]), [0, 0, 0, 0, 0], R, [0, 0, 1], (np.int64(64), 48))
    R[0, 0] = 5.0
    assert camera.R[0, 0] == 1.0
    assert camera.dist.dtype == np.float64 and camera.size == (64, 48)
    assert type(camera.size[0]) is int
    with pytest.raises(ValueError):
        camera.t[0] = 2.0


def test_with_size_changes_only_the_size():
    camera = front_camera()
    resized = camera.with_size(320, 240)
    assert resized.size == (320, 240)
    np.testing.assert_array_equal(resized.K, camera.K)


def test_rig_order_lookup_project_subset_centres(rig12):
    assert rig12.names == tuple(f"cam_{i}" for i in range(12))
    assert len(rig12) == 12
    assert rig12["cam_10"] is rig12[10] is list(rig12)[10]
    X = subject_points(30)
    projected = rig12.project(X)
    assert projected.shape == (12, 30, 2)
    np.testing.assert_array_equal(projected[3], rig12["cam_3"].project(X))
    subset = rig12.subset(["cam_7", "cam_2"])
    assert subset.names == ("cam_2", "cam_7")
    np.testing.assert_allclose(rig12.centres[5], rig12[5].centre)


def test_rig_unknown_name_lists_known_names(rig12):
    with pytest.raises(KeyError, match="known cameras: cam_0, cam_1"):
        rig12["cam_99"]
    with pytest.raises(KeyError, match="cam_99"):
        rig12.subset(["cam_1", "cam_99"])


def test_rig_rejects_duplicate_names():
    camera = front_camera()
    with pytest.raises(InputError, match="duplicate camera names front"):
        Rig((camera, camera))


def test_camera_rejects_reflection_as_rotation():
    with pytest.raises(InputError, match="not a rotation matrix"):
        Camera("c", np.diag([500.0, 500.0, 1.0]), np.zeros(5), np.diag([1.0, 1.0, -1.0]), np.zeros(3),
               (64, 48))


def test_camera_rejects_scaled_rotation():
    with pytest.raises(InputError, match="not a rotation matrix"):
        Camera("c", np.diag([500.0, 500.0, 1.0]), np.zeros(5), 1.001 * np.eye(3), np.zeros(3), (64, 48))


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("K", np.diag([-500.0, 500.0, 1.0]), "focal lengths must be positive"),
        ("K", [[500.0, 3.0, 32.0], [2.0, 500.0, 24.0], [0.0, 0.0, 1.0]], "upper triangular"),
        ("K", [[500.0, 0.0, 32.0], [0.0, 500.0, 24.0], [0.0, 0.0, 2.0]], "upper triangular"),
        ("K", np.eye(2), r"expected shape \(3, 3\)"),
        ("dist", np.zeros(4), r"expected shape \(5,\)"),
        ("t", [0.0, np.nan, 1.0], "NaN"),
        ("size", (64.0, 48), "two positive integers"),
        ("size", (0, 48), "two positive integers"),
        ("name", "", "non-empty string"),
    ],
)
def test_camera_rejects_bad_fields(field, value, message):
    fields = dict(name="c", K=np.diag([500.0, 500.0, 1.0]), dist=np.zeros(5), R=np.eye(3), t=np.zeros(3),
                  size=(64, 48))
    fields[field] = value
    with pytest.raises(InputError, match=message):
        Camera(**fields)


def test_look_at_rejects_degenerate_geometry():
    with pytest.raises(InputError, match="parallel"):
        Camera.look_at("c", (0.0, 0.0, 3.0), (0.0, 0.0, 0.0), f_px=500.0, size=(64, 48))
    with pytest.raises(InputError, match="same point"):
        Camera.look_at("c", (1.0, 0.0, 3.0), (1.0, 0.0, 3.0), f_px=500.0, size=(64, 48))
