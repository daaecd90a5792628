"""scripts/segmenter_probe.py's image handling, with a stand-in for the network (the model's wheel is not here).

The crop must land back where it was taken, and the fusion must keep exactly the parts the probability
confirms; a mistake in either would make the script's IoUs measure the script, not the segmenter.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
_SPEC = importlib.util.spec_from_file_location("segmenter_probe", REPO / "scripts" / "segmenter_probe.py")
probe = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(probe)


class _LeftHalfNet:
    """Says "person" on the left half of whatever input it is given."""

    def setInput(self, blob):  # noqa: N802 (OpenCV's name)
        self.shape = blob.shape[2:]

    def forward(self):
        height, width = self.shape
        out = np.zeros((1, 1, height, width), np.float32)
        out[..., : width // 2] = 1
        return out


def test_the_network_output_is_mapped_back_onto_the_crop():
    image = np.zeros((200, 300, 3), np.uint8)
    subject = np.zeros((200, 300), bool)
    subject[50:150, 100:140] = True  # a box 100 tall, 40 wide: grown by 1.15, 115 x 46 about (99.5, 119.5)
    probability = probe.person_probability(_LeftHalfNet(), (256, 256), image, subject)
    person = probability > 0.5
    ys, xs = np.nonzero(person)
    assert abs(ys.min() - (99.5 - 57.5)) <= 1 and abs(ys.max() - (99.5 + 57.5)) <= 1
    assert abs(xs.min() - (119.5 - 23)) <= 1 and abs(xs.max() - 119.5) <= 1  # the crop's left half
    assert not person[:, 125:].any() and not person[:35].any()


def test_fusion_keeps_the_confirmed_parts_and_largest_the_biggest():
    mask = np.zeros((60, 60), bool)
    mask[5:40, 5:30] = True  # the subject
    mask[50:53, 50:53] = True  # a speck
    mask[45:55, 5:15] = True  # a smaller part the probability confirms
    probability = np.zeros((60, 60), np.float32)
    probability[0:42, 0:32] = 0.9
    probability[45:55, 5:15] = 0.3
    expected = mask.copy()
    expected[50:53, 50:53] = False
    np.testing.assert_array_equal(probe.confirmed_parts(mask, probability), expected)
    subject = np.zeros_like(mask)
    subject[5:40, 5:30] = True
    np.testing.assert_array_equal(probe.largest_part(mask), subject)
    assert probe.iou(mask, subject) == subject.sum() / mask.sum()
