import cv2
import numpy as np
import pytest

from calib.board import Board, board_image, detect, parse_board
from calib.errors import InputError

PIXELS = 40  # pixels per square of the synthetic images


def test_checkerboard_text_is_parsed():
    board = parse_board("checkerboard:8x5:0.11")
    assert board == Board("checkerboard", 8, 5, 0.11)
    assert board.corner_grid == (8, 5) and board.n_corners == 40 and not board.symmetric
    np.testing.assert_allclose(board.object_points[[0, 1, 8]], [[0, 0, 0], [0.11, 0, 0], [0, 0.11, 0]])
    assert parse_board(board.describe()) == board


def test_charuco_text_is_parsed():
    board = parse_board("charuco:7x5:0.14:0.084:DICT_4X4_50")
    assert board.corner_grid == (6, 4) and board.n_corners == 24
    np.testing.assert_allclose(board.object_points[0], [0.14, 0.14, 0.0])
    assert parse_board(board.describe()) == board


def test_a_board_turning_into_itself_is_called_symmetric():
    assert parse_board("checkerboard:7x5:0.1").symmetric
    assert not parse_board("checkerboard:4x7:0.1").symmetric


@pytest.mark.parametrize(("text", "message"), [
    ("chess:8x5:0.1", "unknown board kind"),
    ("checkerboard:8x5", "2 fields, expected 3"),
    ("checkerboard:8-5:0.1", "is not COLSxROWS"),
    ("checkerboard:1x5:0.1", "at least 2"),
    ("checkerboard:8x5:ten", "is not a number"),
    ("checkerboard:8x5:110", "expected metres"),
    ("charuco:7x5:0.1:0.12:DICT_4X4_50", "not smaller than the square"),
    ("charuco:7x5:0.1:0.07:DICT_9X9_1", "not one of OpenCV's ArUco dictionaries"),
    ("charuco:20x20:0.1:0.07:DICT_4X4_50", "has only 50"),
])
def test_bad_board_text_is_refused_in_one_line(text, message):
    with pytest.raises(InputError, match=message):
        parse_board(text)


def test_charuco_picture_is_opencvs():
    board = parse_board("charuco:9x6:0.11:0.077:DICT_4X4_50")
    mine = board_image(board, 100, margin_squares=0)
    opencv = cv2.aruco.CharucoBoard((9, 6), 0.11, 0.077,
                                    cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)).generateImage((900, 600))
    np.testing.assert_array_equal(mine, opencv)


def photographed(board: Board, H: np.ndarray, size=(640, 480)) -> tuple[np.ndarray, np.ndarray]:
    """(image, true corner pixels (N, 2)) of the printed board mapped by the homography ``H`` (board metres ->
    pixels), anti-aliased by rendering at 4x and averaging."""
    picture = board_image(board, PIXELS, margin_squares=1.0)
    margin = PIXELS * 1.0
    origin = board.pattern_origin_m
    to_picture = np.array([[PIXELS / board.square_m, 0, margin - 0.5 - origin[0] * PIXELS / board.square_m],
                           [0, PIXELS / board.square_m, margin - 0.5 - origin[1] * PIXELS / board.square_m],
                           [0, 0, 1]])  # board metres -> picture pixels (centres at integers)
    fine = np.diag([4.0, 4.0, 1.0]) @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    fine = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]]) @ fine  # pixel centres at integers at 4x
    warp = fine @ H @ np.linalg.inv(to_picture)
    big = cv2.warpPerspective(picture, warp, (size[0] * 4, size[1] * 4), flags=cv2.INTER_LINEAR, borderValue=128)
    image = cv2.resize(big, size, interpolation=cv2.INTER_AREA)
    corners = cv2.perspectiveTransform(board.object_points[:, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
    return image, corners


def tilted_view(size=(640, 480)) -> np.ndarray:
    """A board-metres-to-pixels homography: the board seen at an angle."""
    source = np.array([[0, 0], [0.9, 0], [0.9, 0.6], [0, 0.6]], dtype=np.float32)
    target = np.array([[150, 110], [470, 140], [440, 370], [170, 340]], dtype=np.float32)
    return cv2.getPerspectiveTransform(source, target)


@pytest.mark.parametrize("text", ["checkerboard:8x5:0.1", "charuco:9x6:0.1:0.07:DICT_4X4_50"])
def test_detected_corners_are_where_the_board_is(text):
    board = parse_board(text)
    image, truth = photographed(board, tilted_view())
    found = detect(board, image)
    assert found is not None and len(found.ids) >= 30
    errors = np.linalg.norm(found.corners - truth[found.ids], axis=1)
    assert errors.max() < 0.15


def test_checkerboard_corners_keep_their_ids_when_the_board_turns_half_round():
    board = parse_board("checkerboard:8x5:0.1")
    H = tilted_view()
    turn = np.array([[-1, 0, 639], [0, -1, 479], [0, 0, 1]], dtype=float)  # the image rotated by 180 degrees
    for view in (H, turn @ H):
        image, truth = photographed(board, view)
        found = detect(board, image)
        np.testing.assert_allclose(found.corners, truth[found.ids], atol=0.15)


def test_partly_seen_charuco_board_is_found():
    board = parse_board("charuco:9x6:0.1:0.07:DICT_4X4_50")
    image, truth = photographed(board, tilted_view())
    image[:, 320:] = 128  # the right half hidden
    found = detect(board, image)
    assert found is not None and 6 <= len(found.ids) < board.n_corners
    np.testing.assert_allclose(found.corners, truth[found.ids], atol=0.15)


@pytest.mark.parametrize("text", ["checkerboard:8x5:0.1", "charuco:9x6:0.1:0.07:DICT_4X4_50"])
def test_no_board_no_detection(text):
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 3)
    assert detect(parse_board(text), image) is None


def test_large_images_are_searched_smaller_and_refined_at_full_size():
    board = parse_board("checkerboard:4x7:0.025")  # a printed A4 board, portrait phone frames
    source = np.array([[0, 0], [0.1, 0], [0.1, 0.175], [0, 0.175]], dtype=np.float32)
    target = np.array([[300, 500], [800, 560], [760, 1400], [330, 1350]], dtype=np.float32)
    image, truth = photographed(board, cv2.getPerspectiveTransform(source, target), size=(1088, 1920))
    found = detect(board, image)
    assert found is not None
    np.testing.assert_allclose(found.corners, truth[found.ids], atol=0.2)
