"""A clean plate checked against its camera's frames before it is trusted as the background.

A plate is taken before or after the recording, and the camera may have moved in between (a tripod knocked, a
camera re-aimed): every edge of the room then differs from the frames by the shift, and background subtraction
takes those edges for the person, in every frame. Or the plate is another camera's, or another session's. Both
show in the phase correlation of the plate with a frame of its camera (:func:`plate_fit`): the peak's position is
the shift between them, to a fraction of a pixel on a textured room, and its height how much of the two images is
the same picture moved: a plate of the same view scores several times :data:`MIN_PLATE_MATCH` whatever the
person, the noise, flicker and compression of the frame, another view's next to nothing. The person is a small
part of a frame and does not move the peak.

A camera that pans or tilts by a fraction of a degree moves its image by a nearly uniform shift, which
:func:`shifted_plate` undoes; a roll about the optical axis would need a rotation as well, and is rarer on a
tripod.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: A plate this far off its frames (pixels) or further is shifted onto them; closer, the silhouettes' own
#: allowance for a background shifted by a fraction of a pixel (``SilhouetteParams.background_jitter_px``) covers it.
PLATE_SHIFT_PX = 0.5
#: A plate whose phase correlation with its frames peaks below this is not a picture of their view.
MIN_PLATE_MATCH = 0.1
#: A plate with less colour than this share of its frames' (:func:`colour_level`) is a grey-level copy of a colour view:
#: every coloured part of the room would differ from it as much as the person does.
MIN_PLATE_COLOUR = 0.25
#: Frames with less colour than this (grey levels) are a monochrome camera's, for which a plate has none either.
MONOCHROME_LEVELS = 2.0


@dataclass(frozen=True)
class PlateFit:
    """Where a plate lies against a frame of its camera: ``shift`` (x, y) pixels, the frame's content at the plate's
    plus this, and ``match``, the height of the phase correlation's peak (0 to 1); and whether it is
    ``colourless`` against a frame in colour (a grey-level copy, :data:`MIN_PLATE_COLOUR`)."""

    shift: tuple[float, float]
    match: float
    colourless: bool = False

    @property
    def distance_px(self) -> float:
        return float(np.hypot(*self.shift))


def plate_fit(plate: np.ndarray, frame: np.ndarray) -> PlateFit:
    """The :class:`PlateFit` of a clean ``plate`` against a ``frame`` of the same camera, (H, W, 3) uint8 each;
    ``colourless`` when the frame has colour (`MONOCHROME_LEVELS`) and the plate next to none (`MIN_PLATE_COLOUR`).

    On grey levels at full resolution (at a reduced one, aliasing biases the peak's position), on the largest
    middle part whose sides the Fourier transform is fast on (:func:`_fast_length`: 768 x 576 of a 780 x 580
    image), windowed (Hann) so that its borders make no edge of their own.
    """
    height, width = plate.shape[:2]
    size = (_fast_length(width), _fast_length(height))
    x0, y0 = (width - size[0]) // 2, (height - size[1]) // 2
    plate_grey, frame_grey = (cv2.cvtColor(image[y0:y0 + size[1], x0:x0 + size[0]], cv2.COLOR_BGR2GRAY)
                              .astype(np.float32) for image in (plate, frame))
    window = cv2.createHanningWindow(size, cv2.CV_32F)
    (dx, dy), match = cv2.phaseCorrelate(plate_grey, frame_grey, window)
    frame_colour = colour_level(frame)
    colourless = frame_colour > MONOCHROME_LEVELS and colour_level(plate) < MIN_PLATE_COLOUR * frame_colour
    return PlateFit((float(dx), float(dy)), float(match), colourless)


def colour_level(image: np.ndarray) -> float:
    """How coloured an (H, W, 3) uint8 image is: the standard deviations of B − G and G − R over it, summed (grey
    levels), on every fourth pixel of every fourth row. A grey image has none, and neither has a monochrome
    camera's video, whose codec may leave the channels a constant step apart."""
    sample = image[::4, ::4].astype(np.float32)
    return float(np.std(sample[..., 0] - sample[..., 1]) + np.std(sample[..., 1] - sample[..., 2]))


def _fast_length(length: int) -> int:
    """The largest length up to ``length`` that OpenCV's Fourier transform takes as it is (a product of 2, 3 and
    5: :func:`cv2.getOptimalDFTSize` returns it unchanged)."""
    fast = length
    while cv2.getOptimalDFTSize(fast) != fast:
        fast -= 1
    return fast


def shifted_plate(plate: np.ndarray, shift: tuple[float, float]) -> np.ndarray:
    """``plate`` (H, W, 3) uint8 moved by ``shift`` (x, y) pixels onto its frames (:attr:`PlateFit.shift`), the
    strip it uncovers filled with its edge pixels."""
    height, width = plate.shape[:2]
    move = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
    return cv2.warpAffine(plate, move, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
