"""A contact sheet of every camera of a capture at one frame, to look at a capture at a glance."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from pipeline.io.capture import Capture

# Each camera's tile is scaled to this width (pixels) in the montage.
TILE_WIDTH = 390


def montage(capture_dir: Path, frame: int, *, masks: bool = False) -> np.ndarray:
    """(H, W, 3) uint8 BGR grid of all cameras' images at ``frame``, each labelled with its name.

    With ``masks``, the true masks of a synthetic capture (``groundtruth/masks``) are outlined in green.
    """
    capture = Capture.open(capture_dir)
    tiles = []
    for camera in capture.rig.names:
        _, image = next(iter(capture.iter_images(camera, [frame])))
        image = image.copy()
        if masks:
            mask = cv2.imread(str(Path(capture_dir) / "groundtruth" / "masks" / camera / f"{frame:06d}.png"), 0)
            if mask is not None:
                contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
                cv2.drawContours(image, contours, -1, (0, 255, 0), 1)
        scale = TILE_WIDTH / image.shape[1]
        tile = cv2.resize(image, (TILE_WIDTH, round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        cv2.putText(tile, f"{camera}  frame {frame}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3)
        cv2.putText(tile, f"{camera}  frame {frame}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        tiles.append(tile)
    columns = math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / columns)
    height = max(tile.shape[0] for tile in tiles)
    sheet = np.full((rows * height, columns * TILE_WIDTH, 3), 40, dtype=np.uint8)
    for k, tile in enumerate(tiles):
        row, column = divmod(k, columns)
        sheet[row * height : row * height + tile.shape[0], column * TILE_WIDTH : (column + 1) * TILE_WIDTH] = tile
    return sheet
