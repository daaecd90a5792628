import dataclasses

import numpy as np
import pytest
from sphere_scene import CENTRE, RADIUS, VOLUME, render_spheres, ring_rig

from calib.camera import Camera, Rig
from calib.errors import InputError
from stages.reconstruction import Observations, ReconstructionParams, reconstruct, usable_observations


@pytest.fixture(scope="module")
def rig():
    return ring_rig(6)


@pytest.fixture(scope="module")
def sphere_masks(rig):
    return [render_spheres(camera, CENTRE, RADIUS) for camera in rig]


def _radial_errors(observations: Observations, centre=CENTRE, radius=RADIUS):
    """(distance to the sphere (N,) metres, normal angle to the radial direction (N,) degrees)."""
    offsets = observations.points - centre
    distances = np.linalg.norm(offsets, axis=1)
    cosines = np.einsum("ij,ij->i", offsets / distances[:, None], observations.normals)
    return distances - radius, np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))


def _assert_well_formed(observations: Observations, at_most: int):
    assert observations.points.dtype == np.float64 and observations.normals.dtype == np.float64
    assert observations.points.shape == observations.normals.shape == (len(observations), 3)
    assert len(observations) <= at_most
    assert np.all(np.isfinite(observations.points)) and np.all(np.isfinite(observations.normals))
    if len(observations):
        assert np.allclose(np.linalg.norm(observations.normals, axis=1), 1.0)


def test_visual_shape_of_a_sphere_lies_on_it_with_radial_normals(rig, sphere_masks):
    # 1 px is about 1 cm at 4 m with these 390 x 290 images.
    observations = reconstruct(sphere_masks, rig, VOLUME, ReconstructionParams(n_observations=500))
    _assert_well_formed(observations, 500)
    assert len(observations) >= 400
    distance, angle = _radial_errors(observations)
    assert np.median(np.abs(distance)) < 0.002
    assert np.percentile(np.abs(distance), 90) < 0.005
    assert np.median(angle) < 3.0
    assert np.percentile(angle, 90) < 8.0


def test_osculating_rim_placement_beats_the_midpoint(rig, sphere_masks):
    results = {}
    for placement in ("osculating", "midpoint"):
        params = ReconstructionParams(n_observations=500, rim_placement=placement)
        results[placement] = np.median(_radial_errors(reconstruct(sphere_masks, rig, VOLUME, params))[1])
    assert results["osculating"] < 0.6 * results["midpoint"]


def test_visual_shape_through_distorted_lenses():
    rig = ring_rig(6, distortion=True)
    masks = [render_spheres(camera, CENTRE, RADIUS) for camera in rig]
    observations = reconstruct(masks, rig, VOLUME, ReconstructionParams(n_observations=300))
    distance, angle = _radial_errors(observations)
    assert len(observations) >= 250
    assert np.median(np.abs(distance)) < 0.002 and np.median(angle) < 3.0


@pytest.mark.parametrize("method", ["visual_shape", "visual_hull"])
def test_skewed_cameras_reconstruct_as_well_as_unskewed_ones(rig, sphere_masks, method):
    # 8 px of skew on f = 380 px: ten times what decomposed studio calibrations carry, so that a model
    # that ignored it would misplace points by centimetres.
    skewed = ring_rig(6, distortion=True, skew_px=8.0)
    masks = [render_spheres(camera, CENTRE, RADIUS) for camera in skewed]
    params = ReconstructionParams(method=method, n_observations=500, voxel_size_m=0.01)
    errors = {}
    for name, (cameras, views) in {"plain": (rig, sphere_masks), "skewed": (skewed, masks)}.items():
        observations = reconstruct(views, cameras, VOLUME, params)
        assert len(observations) >= 400
        distance, angle = _radial_errors(observations)
        errors[name] = (np.median(np.abs(distance)), np.median(angle))
    assert errors["skewed"][0] < 1.1 * errors["plain"][0] and errors["skewed"][1] < errors["plain"][1] + 0.5


def test_visual_hull_of_a_sphere_encloses_it_tightly(rig, sphere_masks):
    params = ReconstructionParams(method="visual_hull", n_observations=800, voxel_size_m=0.01)
    observations = reconstruct(sphere_masks, rig, VOLUME, params)
    _assert_well_formed(observations, 800)
    assert len(observations) >= 700
    distance, angle = _radial_errors(observations)
    # The hull of six cones contains the sphere (up to a voxel) and bulges out between the rims.
    assert distance.min() > -0.01
    assert np.median(distance) < 0.01 and np.percentile(distance, 95) < 0.05
    assert np.median(angle) < 15.0


def _nearest_sphere(points, centres, radii):
    """(index of the nearest sphere (N,), distance to its surface (N,) metres)."""
    distances = np.abs(np.stack([np.linalg.norm(points - c, axis=1) - r for c, r in zip(centres, radii, strict=True)]))
    return np.argmin(distances, axis=0), np.min(distances, axis=0)


def test_two_spheres_give_points_on_both(rig):
    centres = np.array([[-0.35, 0.0, 1.0], [0.35, 0.1, 1.1]])
    radii = np.array([0.15, 0.2])
    masks = [render_spheres(camera, centres, radii) for camera in rig]
    observations = reconstruct(masks, rig, VOLUME, ReconstructionParams(n_observations=400))
    nearest, distance = _nearest_sphere(observations.points, centres, radii)
    assert np.bincount(nearest, minlength=2).min() > 80
    assert np.mean(distance < 0.01) > 0.97


def test_phantom_edges_of_rays_through_several_hull_parts_are_not_returned(rig):
    # Three spheres make phantom volumes that some contour rays cross besides the rim's own edge
    # (keeping every edge put 2 % of the points more than 3 cm from any sphere).
    centres = np.array([[-0.3, -0.2, 1.0], [0.3, 0.25, 1.05], [0.0, 0.4, 0.9]])
    radii = np.array([0.12, 0.15, 0.1])
    masks = [render_spheres(camera, centres, radii) for camera in rig]
    observations = reconstruct(masks, rig, VOLUME, ReconstructionParams(n_observations=400))
    assert len(observations) >= 380
    _, distance = _nearest_sphere(observations.points, centres, radii)
    assert distance.max() < 0.03
    assert np.mean(distance < 0.01) > 0.97


def test_n_observations_sets_the_count(rig, sphere_masks):
    for wanted in (50, 200):
        observations = reconstruct(sphere_masks, rig, VOLUME, ReconstructionParams(n_observations=wanted))
        assert 0.8 * wanted <= len(observations) <= wanted


@pytest.mark.parametrize("method", ["visual_shape", "visual_hull"])
def test_an_empty_view_empties_the_hull_unless_tolerated(rig, sphere_masks, method):
    masks = list(sphere_masks)
    masks[2] = np.zeros_like(masks[2])
    strict = reconstruct(masks, rig, VOLUME, ReconstructionParams(method=method, n_observations=200))
    _assert_well_formed(strict, 200)
    assert len(strict) == 0
    tolerant = reconstruct(
        masks, rig, VOLUME, ReconstructionParams(method=method, n_observations=200, tolerated_views=1)
    )
    assert len(tolerant) > 100
    # One view fewer makes a looser hull, but it still hugs the sphere.
    assert np.median(np.abs(_radial_errors(tolerant)[0])) < 0.02


@pytest.mark.parametrize("method", ["visual_shape", "visual_hull"])
def test_all_empty_and_all_foreground_masks_give_no_observations(rig, sphere_masks, method):
    params = ReconstructionParams(method=method, n_observations=100)
    empty = [np.zeros_like(mask) for mask in sphere_masks]
    full = [np.full_like(mask, 255) for mask in sphere_masks]
    for masks in (empty, full):
        observations = reconstruct(masks, rig, VOLUME, params)
        _assert_well_formed(observations, 100)
        if masks is empty:
            assert len(observations) == 0


def test_one_all_foreground_view_constrains_nothing(rig, sphere_masks):
    masks = list(sphere_masks)
    masks[0] = np.full_like(masks[0], 255)
    observations = reconstruct(masks, rig, VOLUME, ReconstructionParams(n_observations=300))
    assert len(observations) > 150
    assert np.median(np.abs(_radial_errors(observations)[0])) < 0.005


@pytest.mark.parametrize("method", ["visual_shape", "visual_hull"])
def test_a_view_that_cuts_the_subject_off_does_not_carve_what_it_does_not_see(rig, method):
    """One camera's principal point moved so that the sphere's top lies above its image: its silhouette meets the
    border, and the top is reconstructed from the other views (carved away when a view vetoed its off-image
    part)."""
    K = rig[0].K.copy()
    K[1, 2] -= 150.0
    cameras = list(rig)
    cameras[0] = dataclasses.replace(rig[0], K=K)
    cut_rig = Rig(tuple(cameras))
    masks = [render_spheres(camera, CENTRE, RADIUS) for camera in cut_rig]
    assert masks[0][0].any() and masks[0].any(axis=1).sum() < 0.8 * masks[1].any(axis=1).sum()
    observations = reconstruct(masks, cut_rig, VOLUME, ReconstructionParams(method=method, n_observations=400))
    assert len(observations) > 300
    assert np.median(np.abs(_radial_errors(observations)[0])) < 0.01
    assert observations.points[:, 2].max() > CENTRE[2] + 0.9 * RADIUS  # the top, which the cut view does not see


@pytest.mark.parametrize("method", ["visual_shape", "visual_hull"])
def test_a_view_the_subject_is_wholly_beyond_does_not_carve_him(rig, method):
    """One camera turned away from the sphere: its silhouette is empty, and the sphere, beyond its image, is
    reconstructed from the others; a view that shows him nowhere in its image still carves there."""
    cameras = list(rig)
    cameras[0] = Camera.look_at(rig[0].name, rig[0].centre, rig[0].centre + [0.0, 0.0, -5.0] + [1.0, 0.0, 0.0],
                                f_px=380.0, size=rig[0].size)
    away_rig = Rig(tuple(cameras))
    masks = [render_spheres(camera, CENTRE, RADIUS) for camera in away_rig]
    assert not masks[0].any()
    observations = reconstruct(masks, away_rig, VOLUME, ReconstructionParams(method=method, n_observations=300))
    assert len(observations) > 200 and np.median(np.abs(_radial_errors(observations)[0])) < 0.01


def test_person_outside_the_volume_gives_no_observations(rig, sphere_masks):
    volume = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 2.0]])
    for method in ("visual_shape", "visual_hull"):
        observations = reconstruct(sphere_masks, rig, volume, ReconstructionParams(method=method))
        assert len(observations) == 0


def test_reconstruct_rejects_bad_inputs(rig, sphere_masks):
    params = ReconstructionParams()
    with pytest.raises(InputError, match="one mask per camera"):
        reconstruct(sphere_masks[:-1], rig, VOLUME, params)
    with pytest.raises(InputError, match="cam_1"):
        reconstruct([sphere_masks[0], sphere_masks[1][:-1]] + sphere_masks[2:], rig, VOLUME, params)
    with pytest.raises(InputError, match="volume"):
        reconstruct(sphere_masks, rig, VOLUME[::-1], params)


@pytest.mark.parametrize(
    ("field", "value"),
    [("method", "voxels"), ("n_observations", 10), ("tolerated_views", -1), ("rim_placement", "top"),
     ("voxel_size_m", 0.5)],
)
def test_params_reject_bad_values(field, value):
    with pytest.raises(InputError, match=field):
        ReconstructionParams(**{field: value})


def test_observations_without_a_unit_normal_are_dropped():
    points = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [np.nan, 0.0, 1.0], [0.0, 1.0, 1.0]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.6, 0.8, 0.0]])
    kept_points, kept_normals = usable_observations(points, normals)
    np.testing.assert_array_equal(kept_points, points[[0, 3]])
    np.testing.assert_array_equal(kept_normals, normals[[0, 3]])
