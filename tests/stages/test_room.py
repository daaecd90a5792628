"""Parts of the room changed since a clean plate, found in a camera's silhouettes over the capture."""

import cv2
import numpy as np
import pytest

from stages.background.room import patched_plate, static_parts

SHAPE = (120, 160)
FRAMES = 24
BOX = (slice(70, 100), slice(120, 150))  # rows, columns of a box left in the room


def _person(column: int, arm: int = 0) -> np.ndarray:
    """A standing person's mask with the body's left edge at ``column``, an arm raised ``arm`` pixels."""
    mask = np.zeros(SHAPE, np.uint8)
    cv2.rectangle(mask, (column, 30), (column + 14, 105), 255, -1)
    cv2.circle(mask, (column + 7, 22), 7, 255, -1)
    cv2.line(mask, (column + 14, 40), (column + 30, 60 - arm), 255, 3)
    return mask


def _with_box(mask: np.ndarray) -> np.ndarray:
    mask = mask.copy()
    mask[BOX] = 255
    return mask


def test_a_box_apart_from_the_walking_subject_is_found():
    columns = np.linspace(5, 70, FRAMES).round().astype(int)
    masks = [_with_box(_person(column)) for column in columns]
    region, apart = static_parts(masks)
    box = np.zeros(SHAPE, bool)
    box[BOX] = True
    assert region[box].all()
    assert not region[:, :100].any()  # where the subject walks
    assert apart == list(range(FRAMES))


def test_a_box_the_subject_passes_before_for_a_third_of_the_frames_is_found_and_those_frames_left_out():
    columns = np.linspace(5, 140, FRAMES).round().astype(int)  # from the left to past the box
    masks = [_with_box(_person(column)) for column in columns]
    region, apart = static_parts(masks)
    assert region[BOX].all()
    box = np.zeros(SHAPE, np.uint8)
    box[BOX] = 255
    near = cv2.distanceTransform(cv2.bitwise_not(box), cv2.DIST_L2, 3)  # pixels to the box
    gaps = [near[_person(column) > 0].min() for column in columns]
    assert 0 < sum(gap < 1 for gap in gaps) < FRAMES / 2  # he passes before it
    assert all(gaps[k] > 2 for k in apart)
    assert all(gaps[k] < 9 for k in range(FRAMES) if k not in apart)  # within two blocks


def test_a_subject_standing_still_while_an_arm_moves_is_not_the_room():
    masks = [_person(60, arm=int(30 * np.sin(k / 3))) for k in range(FRAMES)]
    region, apart = static_parts(masks)
    assert not region.any() and apart == []


def test_nothing_is_decided_when_nothing_moves():
    masks = [_with_box(_person(60))] * FRAMES  # the subject never moves: no frame says what is his
    region, apart = static_parts(masks)
    assert not region.any() and apart == []


def test_no_part_without_a_persistent_one():
    masks = [_person(int(column)) for column in np.linspace(5, 140, FRAMES)]
    region, _ = static_parts(masks)
    assert not region.any()
    with pytest.raises(ValueError, match="at least one frame"):
        static_parts([])


def test_the_patch_is_the_frames_at_the_plates_exposure():
    rng = np.random.default_rng(0)
    plate = rng.uniform(40, 200, (*SHAPE, 3)).astype(np.uint8)
    region = np.zeros(SHAPE, bool)
    region[BOX] = True
    box_colour = np.array([60.0, 90.0, 140.0])  # as the plate's exposure would show it
    gains = np.array([[1.2, 1.1, 1.15], [0.9, 0.95, 0.85], [1.05, 1.0, 1.1]])  # each frame exposed otherwise
    frames, masks = [], []
    for k, gain in enumerate(gains):
        frame = plate.astype(np.float32) * gain
        frame[region] = box_colour * gain
        person = _person(10 + 20 * k)
        frame[person > 0] = 250.0  # the subject, elsewhere
        frames.append(np.clip(frame.round(), 0, 255).astype(np.uint8))
        masks.append(_with_box(person))
    patched = patched_plate(plate, region, frames, masks)
    assert np.array_equal(patched[~region], plate[~region])
    assert np.abs(patched[region].astype(float) - box_colour).max() <= 1.5
