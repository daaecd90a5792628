import numpy as np
import pytest
from sphere_scene import RADIUS, VOLUME, render_spheres, ring_rig

from calib.errors import InputError
from stages.reconstruction import ReconstructionParams, reconstruct
from stages.reconstruction.contours import outline
from stages.reconstruction.occlusion import MIN_CAMERAS, hidden_parts, hidden_votes, no_votes, search_hidden_parts

#: The subject, a ball, crosses camera 0's view at this height, ...
PATH = [np.array([0.1 * np.sin(3 * y), y, 1.0]) for y in np.linspace(-0.6, 0.6, 16)]
#: ... or walks straight at it (camera 0 stands on the x axis), keeping to the same part of its image.
TOWARDS = [np.array([x, 0.1 * np.sin(3 * x), 1.0]) for x in np.linspace(-0.6, 0.6, 16)]
#: Camera 0 sees everything below this image row behind a desk.
DESK_ROW = 150


@pytest.fixture(scope="module")
def rig():
    return ring_rig(6)


def frames_seen(rig, path=PATH, desk_row=None, desks=None):
    """Per frame, every camera's silhouette of the ball, camera 0's without the rows below ``desk_row``, or each
    camera of ``desks`` (camera -> row) without the rows below its row."""
    desks = ({0: desk_row} if desk_row is not None else {}) if desks is None else desks
    frames = []
    for centre in path:
        masks = [render_spheres(camera, centre, RADIUS) for camera in rig]
        for camera, row in desks.items():
            masks[camera][row:] = 0
        frames.append(masks)
    return frames


def searched(rig, frames):
    votes = no_votes(list(rig))
    for masks in frames:
        votes = votes + hidden_votes(masks, list(rig), VOLUME)
    return hidden_parts(votes, list(rig))


def test_what_a_desk_hides_from_one_camera_is_found_in_that_camera_only(rig):
    frames = frames_seen(rig, desk_row=DESK_ROW)
    parts = searched(rig, frames)
    assert all(part is None for part in parts[1:])
    found = parts[0] > 0
    assert found.shape == (rig[0].size[1], rig[0].size[0])
    # Where the ball went behind the desk, and nothing of what the camera saw of it above the desk.
    behind = np.maximum.reduce([render_spheres(rig[0], centre, RADIUS) for centre in PATH]) > 0
    behind[:DESK_ROW] = False
    assert (found & behind).sum() > 0.8 * behind.sum()
    assert not found[:DESK_ROW - 2 * 4].any()  # a cell (4 px here) and its growth above the desk's edge at most


def test_a_desk_before_two_cameras_is_found_in_both_in_turn():
    # Camera 3's desk hides more of the ball than camera 0's: the part only camera 3 misses is found first, and
    # with it counted inside, camera 0's, which camera 3 misses too.
    rig = ring_rig(8)
    desks = {0: DESK_ROW, 3: DESK_ROW - 15}
    frames = frames_seen(rig, desks=desks)
    once = searched(rig, frames)
    assert [index for index, part in enumerate(once) if part is not None] == [3]
    parts = search_hidden_parts(lambda: iter(frames), list(rig), VOLUME)
    assert [index for index, part in enumerate(parts) if part is not None] == [0, 3]
    for camera, row in desks.items():
        behind = np.maximum.reduce([render_spheres(rig[camera], centre, RADIUS) for centre in PATH]) > 0
        behind[:row] = False
        assert (parts[camera] > 0)[behind].mean() > 0.8


def test_nothing_is_found_where_every_camera_sees_the_subject(rig):
    assert all(part is None for part in searched(rig, frames_seen(rig)))


def test_the_room_the_others_leave_around_a_subject_who_keeps_to_one_part_of_the_image_is_not_hidden(rig):
    # Five cones leave room around a ball that camera 0 sees as background, on the same cells at every frame.
    assert all(part is None for part in searched(rig, frames_seen(rig, TOWARDS)))


def test_nothing_is_found_with_fewer_cameras_than_the_search_needs():
    small = ring_rig(MIN_CAMERAS - 1)
    assert all(part is None for part in searched(small, frames_seen(small, desk_row=DESK_ROW)))


def test_a_part_one_camera_misses_on_a_single_frame_is_not_hidden(rig):
    frames = frames_seen(rig)
    frames[5][0][DESK_ROW:] = 0
    assert all(part is None for part in searched(rig, frames))


def test_the_outline_along_a_hidden_part_casts_no_ray(rig):
    mask = frames_seen(rig, desk_row=DESK_ROW)[8][0]
    hidden = np.zeros_like(mask)
    hidden[DESK_ROW:] = 255
    plain, beside = outline(mask, smoothing_px=2.0), outline(mask, smoothing_px=2.0, hidden=hidden)
    on_edge = plain.pixels[:, 1] > DESK_ROW - 2
    assert on_edge.any() and plain.usable[on_edge].all()
    assert not beside.usable[on_edge].any()
    assert np.array_equal(beside.usable[~on_edge], plain.usable[~on_edge])


def test_a_hidden_part_no_longer_carves_the_subject(rig):
    masks = frames_seen(rig, desk_row=DESK_ROW)[8]
    centre = PATH[8]
    params = ReconstructionParams()
    carved = reconstruct(masks, rig, VOLUME, params)
    hidden = [None] * len(rig)
    hidden[0] = np.zeros_like(masks[0])
    hidden[0][DESK_ROW:] = 255
    whole = reconstruct(masks, rig, VOLUME, params, hidden)
    # Without the part, camera 0 carves the ball's lower half away; with it, the points cover the ball again.
    lowest = centre[2] - 0.8 * RADIUS
    assert (carved.points[:, 2] < lowest).sum() < 0.2 * (whole.points[:, 2] < lowest).sum()
    distances = np.linalg.norm(whole.points - centre, axis=1) - RADIUS
    assert np.median(np.abs(distances)) < 0.01 and np.percentile(np.abs(distances), 90) < 0.03


def test_hidden_parts_must_fit_the_cameras(rig):
    masks = frames_seen(rig)[0]
    with pytest.raises(InputError, match="one map per camera"):
        reconstruct(masks, rig, VOLUME, ReconstructionParams(), [None] * (len(rig) - 1))
