from dataclasses import replace

import cv2
import numpy as np
import pytest
from still_scene import VOLUME, ellipsoid_mask, ring

from calib.errors import InputError
from stages.consistency import consistent_silhouettes, explained_share


def render_spheres(camera, centres, radii):
    masks = [ellipsoid_mask(camera, centre, [radius] * 3) for centre, radius in zip(centres, radii, strict=True)]
    return np.maximum.reduce(masks)

BODY = np.array([0.1, -0.05, 1.0])
HAND = np.array([0.1, 0.45, 1.3])  # 25 cm from the body's surface: a separate part in most views


@pytest.fixture(scope="module")
def scene():
    rig = ring(6)
    masks = [render_spheres(camera, [BODY, HAND], [0.25, 0.08]) for camera in rig]
    return rig, masks


def test_parts_every_view_confirms_are_kept(scene):
    rig, masks = scene
    checked = consistent_silhouettes(masks, list(rig), VOLUME, tolerated=1)
    assert all(np.array_equal(a, b) for a, b in zip(checked, masks, strict=True))


def test_a_bystander_seen_by_two_cameras_is_dropped_from_both(scene):
    rig, masks = scene
    bystander = np.array([-1.0, 0.9, 0.9])  # inside the volume, seen by every camera, drawn into two
    seen = [render_spheres(camera, [bystander], [0.25]) for camera in rig]
    with_bystander = [np.maximum(mask, blob) if index in (0, 3) else mask
                      for index, (mask, blob) in enumerate(zip(masks, seen, strict=True))]
    assert all((with_bystander[index] > masks[index]).sum() > 100 for index in (0, 3))  # separate blobs
    checked = consistent_silhouettes(with_bystander, list(rig), VOLUME, tolerated=1)
    assert all(np.array_equal(a, b) for a, b in zip(checked, masks, strict=True))


def test_a_blob_in_one_view_goes_and_the_subject_stays_when_that_view_misses_a_part(scene):
    rig, masks = scene
    masks = [mask.copy() for mask in masks]
    cv2.circle(masks[2], (20, 20), 8, 255, -1)  # a reflection
    masks[4][render_spheres(rig[4], [HAND], [0.08]) > 0] = 0  # one view misses the hand: tolerated
    checked = consistent_silhouettes(masks, list(rig), VOLUME, tolerated=1)
    assert checked[2][20, 20] == 0 and (checked[2] > 0).sum() == (masks[2] > 0).sum() - (masks[2][5:36, 5:36] > 0).sum()
    assert all(np.array_equal(checked[index], masks[index]) for index in (0, 1, 3, 4, 5))


def test_a_view_is_not_emptied_of_the_subject_merged_with_something_the_others_do_not_see(scene):
    rig, masks = scene
    masks = [mask.copy() for mask in masks]
    x, y, w, h = cv2.boundingRect(masks[1])
    thing = np.zeros_like(masks[1])  # in this view only: a large box away from the subject, joined to him by a strip
    thing[75:115, 2:42] = 255
    thing[y + h // 2:y + h // 2 + 2, 40:x + w // 2] = 255
    thing[y + h // 2:76, 40:42] = 255
    merged = np.maximum(masks[1], thing)
    masks[1] = merged.copy()
    cv2.circle(masks[1], (150, 110), 5, 255, -1)  # and a speck
    checked = consistent_silhouettes(masks, list(rig), VOLUME, tolerated=1)
    # Their part holds more of the box than of the subject and alone would not pass; the speck goes.
    assert np.array_equal(checked[1], merged)


def test_one_mask_per_camera():
    rig = ring(3)
    with pytest.raises(InputError, match="2 masks for 3 cameras"):
        consistent_silhouettes([np.zeros((120, 160), np.uint8)] * 2, list(rig), VOLUME, tolerated=0)


def test_the_visual_hull_explains_the_silhouettes_of_a_consistent_rig_only(scene):
    rig, masks = scene
    cameras = list(rig)
    assert explained_share(masks, cameras, VOLUME, tolerated=0, rays_per_view=100) > 0.95  # outline pixels may miss
    turn, _ = cv2.Rodrigues(np.radians(2.0) * np.array([0.0, 0.6, 0.8]))
    turned = [replace(camera, R=turn @ camera.R, t=-(turn @ camera.R) @ camera.centre) if index % 2 else camera
              for index, camera in enumerate(cameras)]
    assert explained_share(masks, turned, VOLUME, tolerated=0, rays_per_view=100) < 0.9
    assert np.isnan(explained_share([np.zeros_like(mask) for mask in masks], cameras, VOLUME, tolerated=0,
                                    rays_per_view=100))
