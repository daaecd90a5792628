"""Measure a learned person segmenter against plate-free background subtraction (issue #15), without shipping it.

The only person segmenter a registry package ships is mediapipe 0.10.x's selfie model
(``mediapipe/modules/selfie_segmentation/``, Apache-2.0), in a square (256 x 256) and a landscape
(256 x 144) variant; OpenCV's dnn module reads it, so no mediapipe import is needed. The network wants
the person to fill its input, so it runs on a crop around the subject, mapped onto the whole input
(stretched: the tall box fills the input's width too). Per foreign capture this prints the median IoU
with ``groundtruth/masks`` of

- ``background``: the silhouette stage's masks of a run without the capture's clean plates;
- ``square``/``landscape``: the segmenter alone on the box of those masks (a box a background gives);
- ``tracked``: the segmenter alone, its box taken from its own mask of the previous frame (the first
  frame: the whole image, then twice its own box), every frame: what ``method: segment`` would be;
- ``fused``: the background masks without the connected parts where the segmenter's mean probability is
  below ``FUSED_MIN_PROBABILITY``, and ``largest``: those masks' largest connected part alone (no model);

with the segmenter's process CPU time per image (single-threaded OpenCV, crop and resampling included).

Usage (the plate-free runs: ``cp -r CAPTURE NOPLATE && rm -r NOPLATE/background``, then
``python -m pipeline run NOPLATE --out RUNS/<capture> --to silhouettes``)::

    pip download mediapipe==0.10.14 --no-deps -d WHEELS
    python scripts/segmenter_probe.py --wheel WHEELS/mediapipe-0.10.14-*.whl --runs RUNS [--step 10]
"""

from __future__ import annotations

import argparse
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
FOREIGN = REPO.parent / "shared" / "foreign"
MODELS = {"square": ("selfie_segmentation.tflite", (256, 256)),
          "landscape": ("selfie_segmentation_landscape.tflite", (256, 144))}
# The crop is the subject's box grown by this factor about its centre (tighter boxes score higher, up to
# where a box from an imperfect mask cuts off a hand or a foot).
BOX_GROWTH = 1.15
FUSED_MIN_PROBABILITY = 0.2


def load_net(wheel: Path, name: str) -> cv2.dnn.Net:
    data = zipfile.ZipFile(wheel).read(f"mediapipe/modules/selfie_segmentation/{name}")
    return cv2.dnn.readNetFromTFLite(np.frombuffer(data, np.uint8))


def person_probability(net: cv2.dnn.Net, size: tuple[int, int], image: np.ndarray, box_of: np.ndarray) -> np.ndarray:
    """The segmenter's person probability over the whole image, from a crop around ``box_of``'s pixels."""
    ys, xs = np.nonzero(box_of)
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    half_h, half_w = BOX_GROWTH * (ys.max() - ys.min() + 1) / 2, BOX_GROWTH * (xs.max() - xs.min() + 1) / 2
    corners = np.float32([[cx - half_w, cy - half_h], [cx + half_w, cy - half_h], [cx - half_w, cy + half_h]])
    to_input = cv2.getAffineTransform(corners, np.float32([[0, 0], [size[0], 0], [0, size[1]]]))
    patch = cv2.warpAffine(image, to_input, size, flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REPLICATE)
    net.setInput(cv2.dnn.blobFromImage(patch, 1 / 255.0, size, swapRB=True))
    probability = net.forward().reshape(size[1], size[0])
    height, width = image.shape[:2]
    return cv2.warpAffine(probability, to_input, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def largest_part(mask: np.ndarray) -> np.ndarray:
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8))
    return mask if count <= 1 else labels == 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])


def confirmed_parts(mask: np.ndarray, probability: np.ndarray) -> np.ndarray:
    count, labels = cv2.connectedComponents(mask.astype(np.uint8))
    sums = np.bincount(labels.ravel(), probability.ravel(), count)
    keep = sums >= FUSED_MIN_PROBABILITY * np.bincount(labels.ravel(), None, count)
    keep[0] = False
    return keep[labels]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def probe_capture(capture: Path, run: Path, nets: dict, step: int) -> dict[str, list[float]]:
    scores: dict[str, list[float]] = {k: [] for k in ("background", "square", "landscape", "tracked", "fused",
                                                        "largest", "ms square", "ms landscape")}
    for camera_dir in sorted((capture / "groundtruth" / "masks").iterdir()):
        video = cv2.VideoCapture(str(capture / "videos" / f"{camera_dir.name}.mp4"))
        previous = None
        frame = 0
        while True:
            ok, image = video.read()
            if not ok:
                break
            truth = cv2.imread(str(camera_dir / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            net, size = nets["square"]
            if previous is None:  # start from the whole image, then twice from its own box
                previous = np.ones(truth.shape, bool)
                for _ in range(3):
                    previous = largest_part(person_probability(net, size, image, previous) > 0.5)
                    if not previous.any():
                        previous = np.ones(truth.shape, bool)
            tracked = largest_part(person_probability(net, size, image, previous) > 0.5)
            scores["tracked"].append(iou(tracked, truth))
            previous = tracked if tracked.any() else None
            background = cv2.imread(str(run / "silhouettes" / camera_dir.name / f"{frame:06d}.png"),
                                    cv2.IMREAD_GRAYSCALE) > 0
            if frame % step == 0 and background.any():
                scores["background"].append(iou(background, truth))
                scores["largest"].append(iou(largest_part(background), truth))
                for variant, (net, size) in nets.items():
                    start = time.process_time()
                    probability = person_probability(net, size, image, background)
                    scores[f"ms {variant}"].append(1000 * (time.process_time() - start))
                    scores[variant].append(iou(probability > 0.5, truth))
                    if variant == "square":
                        scores["fused"].append(iou(confirmed_parts(background, probability), truth))
            frame += 1
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--wheel", type=Path, required=True, help="mediapipe 0.10.14 wheel")
    parser.add_argument("--runs", type=Path, required=True, help="folder of plate-free runs, one per capture name")
    parser.add_argument("--foreign", type=Path, default=FOREIGN)
    parser.add_argument("--step", type=int, default=10, help="every step-th frame (the tracked crop: every frame)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    nets = {variant: (load_net(args.wheel, name), size) for variant, (name, size) in MODELS.items()}
    columns = ("background", "square", "landscape", "tracked", "fused", "largest", "ms square", "ms landscape")
    print("| capture | " + " | ".join(columns) + " |")
    print("|---" * (len(columns) + 1) + "|")
    for run in sorted(path for path in args.runs.iterdir() if (path / "silhouettes").is_dir()):
        scores = probe_capture(args.foreign / run.name, run, nets, args.step)
        cells = [f"{np.median(scores[c]):.{1 if c.startswith('ms') else 3}f}" for c in columns]
        print(f"| {run.name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
