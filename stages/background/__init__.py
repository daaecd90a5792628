"""Each camera's background when no clean plate is given, with the subject left out even where he stands still.

The temporal median of a camera's frames is its background wherever the subject covers a pixel in fewer
than half of them. A subject who stays on one spot for a while (standing still before he starts, a stance
held between kicks) covers those pixels in more than half, and the median keeps a ghost of him: the
silhouettes then lose him wherever he stands as the ghost does, and gain a phantom wherever the ghost's
place is bare again.

If we knew which pixels the subject covers in every frame, the background would be the median of each
pixel's frames where it is *not* covered. One view cannot tell where its own background is wrong, but the
views together can: a view's errors are its own (a view's ghost is where the subject stood *as that view
sees it*; the blob where a ghost's place is bare again, or a passer-by, has no counterpart in most other
views), while the subject is where the views agree. So the estimate iterates (:func:`estimate_backgrounds`):

1. each camera's background is the plain median of frames sampled over the whole sequence;
2. each sampled frame's silhouettes are cut against it, at a reduced working resolution;
3. each sampled frame's visual hull is carved on a voxel grid of the working volume: a voxel is kept when
   it lies in the silhouette of every camera that sees it but ``tolerated`` ones (one, from four cameras
   on), so a view whose ghost hides the subject does not carve him away, while what one view alone sees
   is carved;
4. the hull, projected into each view, marks the pixels the subject covers in that frame (the first round
   the hull alone, since the views' own silhouettes may miss him where a ghost matches him; later rounds
   the view's own silhouette where the hull agrees, which is tighter; holes that a cover encloses are
   covered too); each pixel's background becomes the median of its samples that are not covered;
5. back to 2 with the new backgrounds, until the covered pixels settle.

A subject who stood still long enough to be a ghost in most views vanishes from the samples where he stands
as the ghost does: their hulls are empty while the others' are not. Those samples are told from samples in
which nobody was in view (a subject who walks in later) by the outlines of the two candidate backgrounds,
the median of all the samples and the median of the others (:func:`_outlines`): the one that shows the room
has no person's outline along the border where they differ. The estimate then starts again from that one,
or, when neither is clearly the room, leaves those samples out.

A pixel covered in (nearly) every sample is never seen bare: its background is inpainted from the pixels
around it (:func:`cv2.inpaint`), and its share of the image is reported
(:attr:`BackgroundEstimate.unresolved_share`); the subject then stays foreground there, which is right
as long as he stays there. A part of him that never changes colour in any view (he never moves at all)
looks to every sample like the room, and no estimate from the frames can tell it from the room.

Each estimate also measures how much the samples scatter about it (:func:`_scatter`): the silhouettes cut
against it take that as the lowest noise level a frame can have (``BackgroundModel.noise_floor``).

Memory stays flat in the sequence's length: at most ``MAX_SAMPLES`` frames per camera are sampled
(fewer for large images, ``SAMPLE_BYTES``). The working-resolution copies of every camera's samples are
kept; of the full-resolution frames, one camera's at a time (:func:`sample_camera`), and afterwards only
the pixels where the plain median is contested, where more than ``CONTESTED_SHARE`` of the samples differ
from it. Elsewhere the plain median is already the background: the subject covered the pixel too rarely to
move the median, or with a colour too close to the background's to matter; or he covered it in most
samples with one unchanging colour (standing still), and the working-resolution estimate, whose coverage
says so, is used there instead.
"""

from stages.background.estimate import MIN_UNCOVERED, BackgroundEstimate, estimate_backgrounds
from stages.background.hull import tolerated_views, working_camera
from stages.background.samples import CameraSamples, masked_median, sample_camera, sample_count, working_size

__all__ = [
    "MIN_UNCOVERED",
    "BackgroundEstimate",
    "CameraSamples",
    "estimate_backgrounds",
    "masked_median",
    "sample_camera",
    "sample_count",
    "tolerated_views",
    "working_camera",
    "working_size",
]
