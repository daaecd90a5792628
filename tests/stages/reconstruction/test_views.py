import dataclasses

import numpy as np
import pytest
from sphere_scene import ring_rig

from calib.camera import MIN_VIEW_DEPTH_M
from stages.reconstruction.views import (
    VOLUME_FACES,
    blind_beyond_image,
    faces_reached,
    inside_view,
    subject_cut_off,
)


def _inside_view_reference(camera, mask, X):
    """The plain float32 formulation that ``inside_view`` evaluates with fewer passes, on the full image."""
    x, y, z = camera.R.astype(np.float32) @ X + camera.t.astype(np.float32)[:, None]
    seen = z > MIN_VIEW_DEPTH_M
    inverse_z = 1.0 / np.where(seen, z, np.float32(1.0))
    x *= inverse_z
    y *= inverse_z
    k1, k2, p1, p2, k3 = camera.dist.astype(np.float32)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    x, y = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    fx, fy, cx, cy = (np.float32(value) for value in (camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]))
    if camera.K[0, 1]:  # u = fx x + s y + cx, as fx (x + (s / fx) y) + cx
        x = x + np.float32(camera.K[0, 1] / camera.K[0, 0]) * y
    u = fx * x + (cx + np.float32(0.5))
    v = fy * y + (cy + np.float32(0.5))
    height, width = mask.shape
    seen &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    with np.errstate(invalid="ignore"):
        pixel = np.where(seen, v.astype(np.intp) * width + u.astype(np.intp), 0)
    return seen & (mask.ravel()[pixel] > 0)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    camera = ring_rig(3)[0]
    width, height = camera.size
    mask = np.zeros((height, width), np.uint8)
    mask[60:200, 100:300] = np.where(rng.random((140, 200)) < 0.5, np.uint8(255), np.uint8(0))
    # Points around the camera: in front, behind, beside the image, on the image plane.
    X = (camera.centre[:, None] + 4.0 * rng.standard_normal((3, 200_000))).astype(np.float32)
    return camera, mask, X


# Points just in front of the image plane overflow the distortion polynomial: their pixel is meaningless
# (and unused), and casting it warns, as it always did.
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")
@pytest.mark.parametrize(("dist", "skew"), [((0, 0, 0, 0, 0), 0.0), ((-0.2, 0.05, 0, 0, 0.01), 0.0),
                                           ((-0.1, 0.02, 0.002, -0.003, 0.0), 0.0), ((0, 0, 0, 0, 0), 6.0),
                                           ((-0.2, 0.05, 0, 0, 0.01), -4.0)])
def test_inside_view_matches_the_plain_projection_bit_for_bit(scene, dist, skew):
    camera, mask, X = scene
    K = camera.K.copy()
    K[0, 1] = skew
    camera = dataclasses.replace(camera, K=K, dist=np.array(dist, float))
    expected = _inside_view_reference(camera, mask, X)
    assert expected.sum() > 1000  # thousands of points land on foreground pixels
    assert np.array_equal(inside_view(camera, mask, X), expected)
    # The same answers from the box around the foreground, given its corner.
    assert np.array_equal(inside_view(camera, mask[59:201, 99:301], X, (99, 59)), expected)


def test_a_point_gets_the_same_answer_alone_as_in_company(scene):
    camera, mask, X = scene
    together = inside_view(camera, mask, X[:, :3000])
    alone = [inside_view(camera, mask, X[:, i:i + 1])[0] for i in range(3000)]
    assert np.array_equal(together, alone)
    assert len(inside_view(camera, mask, X[:, :0])) == 0


def test_faces_reached_names_the_faces_a_cut_subject_lies_on():
    volume = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]])
    standing = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 1.7]])  # feet on the floor, head below the top
    assert not faces_reached(standing, volume, 0.02).any()
    cut = np.array([[0.0, 0.0, 0.5], [0.99, 0.0, 1.995]])
    assert [name for (_, _, name), hit in zip(VOLUME_FACES, faces_reached(cut, volume, 0.02), strict=True)
                                                if hit] == [
        "+x", "top (+z)"]
    raised = volume + [[0, 0, 0.3], [0, 0, 0]]  # a bottom face above the floor cuts the feet off
    assert faces_reached(standing + [0, 0, 0.3], raised, 0.02)[4]
    assert not faces_reached(np.zeros((0, 3)), volume, 0.02).any()


def test_a_view_blind_beyond_its_image_says_inside_there_and_nothing_else_changes(scene):
    camera, mask, X = scene
    framed = inside_view(camera, mask, X)
    blind = inside_view(camera, mask, X, off_image=True)
    x, y, z = camera.R @ X.astype(float) + camera.t[:, None]
    front = z > MIN_VIEW_DEPTH_M
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = (camera.K @ np.stack([x / z, y / z, np.ones_like(z)]))[:2]
    off = ~front | (u < -0.5) | (u > camera.size[0] - 0.5) | (v < -0.5) | (v > camera.size[1] - 0.5)
    margin = front & ((np.abs(u + 0.5) < 0.01) | (np.abs(u - camera.size[0] + 0.5) < 0.01)
                      | (np.abs(v + 0.5) < 0.01) | (np.abs(v - camera.size[1] + 0.5) < 0.01))
    margin |= np.abs(z - MIN_VIEW_DEPTH_M) < 1e-3
    assert (off & ~front).sum() > 10_000 and (off & front).sum() > 10_000
    assert np.all(blind[off & ~margin]) and not np.any(framed[off & ~margin])
    assert np.array_equal(blind[~off & ~margin], framed[~off & ~margin])  # in the image: as before
    assert np.array_equal(inside_view(camera, mask[59:201, 99:301], X, (99, 59), off_image=True), blind)


@pytest.mark.parametrize(("rows", "columns", "blind"), [((10, 20), (30, 40), False), ((0, 5), (30, 40), True),
                                                        ((10, 20), (95, 100), True), ((95, 100), (0, 100), True),
                                                        ((10, 10), (30, 40), True)])
def test_a_view_is_blind_beyond_its_image_when_its_silhouette_reaches_the_border_or_is_empty(rows, columns, blind):
    mask = np.zeros((100, 100), np.uint8)
    mask[slice(*rows), slice(*columns)] = 255
    assert blind_beyond_image(mask) is blind


@pytest.mark.parametrize(("pieces", "cut"), [
    ([(slice(10, 50), slice(20, 40))], False),  # the whole subject in view
    ([(slice(30, 60), slice(20, 40))], True),  # his feet below the image
    ([(slice(10, 50), slice(20, 40)), (slice(0, 2), slice(50, 53))], False),  # a speck on the border
    ([(slice(10, 50), slice(20, 40)), (slice(20, 30), slice(0, 5))], False),  # a stray blob on the border
    ([], False),  # nobody
])
def test_the_subject_is_cut_off_when_the_largest_piece_of_his_silhouette_reaches_the_border(pieces, cut):
    mask = np.zeros((60, 80), np.uint8)
    for rows, columns in pieces:
        mask[rows, columns] = 255
    assert subject_cut_off(mask) is cut
