"""A box put down in the room after the clean plates were taken, drawn into a capture's frames (``perturb --box``).

The box stands on the floor beside where the subject moves: ``BOX_DISTANCE`` from his mean place (the true pelvis
over the capture), across his main direction of travel (the direction his place varies least in). Every camera
draws it from the capture's calibration, its faces shaded as if lit from above, in every frame and not in the
plates; the subject is drawn over it in the frames where he is nearer the camera than the box's centre, and hidden
by it in the others (his true masks then lose what it hides).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from pipeline.io.capture import Capture
from pipeline.io.export_io import read_joints_csv

#: The box (metres: across, deep, high), its distance from the subject's mean place and its colour (BGR 8-bit levels).
BOX_SIZE = np.array([0.5, 0.4, 0.7])
BOX_DISTANCE = 1.0
BOX_COLOUR = np.array([60.0, 90.0, 140.0], np.float32)
#: Each face's corners (indices of :func:`box_corners`' rows) and its shade, the top lit most.
FACES = (((0, 1, 3, 2), 0.8), ((4, 6, 7, 5), 0.7), ((0, 4, 5, 1), 0.9), ((2, 3, 7, 6), 0.75), ((1, 5, 7, 3), 1.1))
#: A fixed texture on the box (8-bit levels), so that it is not a flat colour.
BOX_TEXTURE = 4.0


@dataclass(frozen=True)
class BoxView:
    """The box as one camera sees it: ``image`` (H, W, 3) float32 where ``region`` (H, W) bool is set, and its centre's
    ``depth`` from the camera (metres)."""

    image: np.ndarray
    region: np.ndarray
    depth: float


def pelvis_track(truth: Path) -> dict[int, np.ndarray]:
    """The true pelvis (3,) of each frame of a ground truth's joints.csv."""
    frames, names, joints = read_joints_csv(truth / "joints.csv")
    if "pelvis" not in names:
        raise InputError(f"{truth / 'joints.csv'}: no pelvis to place the box by")
    column = list(names).index("pelvis")
    return {int(frame): joints[k, column] for k, frame in enumerate(frames)}


def box_corners(pelvis: np.ndarray, volume: np.ndarray) -> np.ndarray:
    """(8, 3) the box's corners (x, y and z each from low to high, z fastest), beside the subject's places ``pelvis``
    (F, 3), within ``volume`` (2, 3) when one of the two sides allows."""
    centre = pelvis[:, :2].mean(axis=0)
    spread = np.cov(pelvis[:, :2].T) if len(pelvis) > 1 else np.eye(2)
    across = np.linalg.eigh(spread)[1][:, 0]  # the direction he moves least along
    for side in (across, -across):
        middle = centre + BOX_DISTANCE * side
        if np.all(middle - BOX_SIZE[:2] / 2 >= volume[0, :2]) and np.all(middle + BOX_SIZE[:2] / 2 <= volume[1, :2]):
            break
    floor = volume[0, 2]
    return np.array([[middle[0] + dx * BOX_SIZE[0] / 2, middle[1] + dy * BOX_SIZE[1] / 2, floor + dz * BOX_SIZE[2]]
                     for dx in (-1, 1) for dy in (-1, 1) for dz in (0, 1)])


def box_view(camera: Camera, corners: np.ndarray) -> BoxView:
    """How ``camera`` sees the box of ``corners`` (8, 3): its faces drawn far to near."""
    width, height = camera.size
    image = np.zeros((height, width, 3), np.float32)
    region = np.zeros((height, width), np.uint8)
    uv = camera.project(corners)
    distance = [np.linalg.norm(corners[list(face)].mean(axis=0) - camera.centre) for face, _ in FACES]
    for index in np.argsort(distance)[::-1]:
        face, shade = FACES[index]
        polygon = np.round(uv[list(face)]).astype(np.int32)
        cv2.fillConvexPoly(image, polygon, tuple(float(level) for level in np.clip(BOX_COLOUR * shade, 0, 255)))
        cv2.fillConvexPoly(region, polygon, 255)
    image += np.random.default_rng(0).normal(0.0, BOX_TEXTURE, (height, width, 1)).astype(np.float32)
    return BoxView(image, region > 0, float(camera.depth(corners.mean(axis=0, keepdims=True))[0]))


def with_box(frame: np.ndarray, view: BoxView, subject: np.ndarray | None, subject_nearer: bool) -> np.ndarray:
    """``frame`` (float32, BGR) with the box drawn in, under the subject's pixels ``subject`` (H, W) bool when he is
    nearer the camera (None: no true mask, the box over everything)."""
    drawn = frame.copy()
    drawn[view.region] = view.image[view.region]
    if subject is not None and subject_nearer:
        drawn[subject] = frame[subject]
    return drawn


@dataclass(frozen=True)
class BoxCamera:
    """The box as one camera sees it, and whether the subject is nearer that camera than the box in a frame."""

    camera: Camera
    view: BoxView
    pelvis: dict[int, np.ndarray]  # the true pelvis by frame
    masks: Path  # the camera's true masks

    def nearer(self, frame: int) -> bool:
        return frame in self.pelvis and float(self.camera.depth(self.pelvis[frame][None])[0]) < self.view.depth

    def subject(self, frame: int) -> tuple[np.ndarray | None, bool]:
        """The subject's true mask (H, W) bool in ``frame`` (None without one), and whether he is nearer."""
        mask = cv2.imread(str(self.masks / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)
        return (None if mask is None else mask > 0), self.nearer(frame)


def box_cameras(capture: Path, kept: set[str]) -> dict[str, BoxCamera]:
    """The box as each of the ``kept`` cameras of ``capture`` sees it (the capture's own calibration), placed by
    its true pelvis track, with its true masks to draw the subject over it."""
    truth = capture / "groundtruth"
    if not (truth / "joints.csv").is_file() or not (truth / "masks").is_dir():
        raise InputError(f"{truth}: no true joints and masks to place the box by and to draw the subject over it")
    source = Capture.open(capture)
    pelvis = pelvis_track(truth)
    corners = box_corners(np.array(list(pelvis.values())), source.volume)
    return {camera.name: BoxCamera(camera, box_view(camera, corners), pelvis, truth / "masks" / camera.name)
            for camera in source.rig if camera.name in kept}
