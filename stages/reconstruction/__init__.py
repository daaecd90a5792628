"""3-D points with outward normals from one frame's silhouettes: the tracker's data.

Two methods:

- ``"visual_shape"`` (the paper's data): rim points on viewing edges, one per sampled outline point,
  with the exact normal of the viewing-cone tangent plane (``visual_shape.py``);
- ``"visual_hull"``: voxel carving with marching cubes, points and normals on the hull's surface
  (``visual_hull.py``); slower and its normals are those of the hull's facets, not of the body.

``reconstruct`` validates its inputs and dispatches; the maths lives in the modules.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from stages.checks import check_bool, check_choice, check_int, check_number
from stages.reconstruction.visual_hull import hull_surface_points
from stages.reconstruction.visual_shape import rim_points

METHODS = ("visual_shape", "visual_hull")
RIM_PLACEMENTS = ("osculating", "midpoint")


@dataclass(frozen=True)
class ReconstructionParams:
    """Parameters of the reconstruction stage.

    Attributes
    ----------
    method : {"visual_shape", "visual_hull"}
        The visual shape's rim points with the exact normals of the viewing cones (the paper's data), or
        points on a carved voxel hull, slower and with the normals of its facets.
    n_observations : int
        How many observations to return (50 to 5000), spread evenly over cameras and outlines; fewer
        when the silhouettes do not support that many.
    tolerated_views : int
        A point still counts as inside the hull when it falls outside this many silhouettes (real
        silhouettes have holes; a camera may miss a hand). 0 = the exact visual hull; at most the cameras
        less two (`check_tolerated_views`).
    rim_placement : {"osculating", "midpoint"}
        Where the visual shape puts the rim point on its viewing edge: from the other cones' tangent
        planes at the edge's ends (see ``visual_shape.py``), or the edge's midpoint.
    samples_per_ray : int
        Samples along each viewing ray's bounded stretch before the in/out transitions are bisected;
        edges shorter than the sample spacing (about 2 cm on a typical 40 cm stretch) can be missed.
    contour_smoothing_px : float
        Gaussian smoothing of outlines along the contour (in contour points), against pixel staircase;
        applied twice (twicing), so that it does not shrink thin limbs (`contours.outline`).
    voxel_size_m, coarse_voxel_size_m : float
        Visual hull: final voxel size and the size carving starts at (metres).
    refine_calibration : bool
        Turn each camera about its centre as the silhouettes' epipolar tangencies say, before reconstructing,
        when that explains them clearly better (`stages.tangency.refine_turns`): a camera knocked or calibrated
        a fraction of a degree off otherwise carves limbs away. The pipeline does it (it needs many frames'
        silhouettes); `reconstruct` takes the rig it is given.
    find_hidden_parts : bool
        Look for parts of each view hidden behind something in front of the subject (a desk, a pillar), where the
        other cameras place him on most frames and this one shows background, and let that view carve nothing
        there (`stages.reconstruction.occlusion`): otherwise whatever goes behind it is carved away for every
        view. The pipeline does it (it needs many frames' silhouettes); `reconstruct` takes the parts it is given.
    """

    method: str = "visual_shape"
    n_observations: int = 1000
    tolerated_views: int = 0
    rim_placement: str = "osculating"
    samples_per_ray: int = 24
    contour_smoothing_px: float = 2.0
    voxel_size_m: float = 0.01
    coarse_voxel_size_m: float = 0.08
    refine_calibration: bool = True
    find_hidden_parts: bool = True

    def __post_init__(self) -> None:
        check_choice("reconstruction.method", self.method, METHODS)
        check_bool("reconstruction.refine_calibration", self.refine_calibration)
        check_bool("reconstruction.find_hidden_parts", self.find_hidden_parts)
        check_choice("reconstruction.rim_placement", self.rim_placement, RIM_PLACEMENTS)
        check_int("reconstruction.n_observations", self.n_observations, 50, 5000)
        check_int("reconstruction.tolerated_views", self.tolerated_views, 0)
        check_int("reconstruction.samples_per_ray", self.samples_per_ray, 2)
        check_number("reconstruction.contour_smoothing_px", self.contour_smoothing_px, 0.0)
        for name in ("voxel_size_m", "coarse_voxel_size_m"):
            check_number(f"reconstruction.{name}", getattr(self, name))  # finite: NaN passes the check below
        if not 0 < self.voxel_size_m <= self.coarse_voxel_size_m:
            raise InputError(
                "reconstruction.voxel_size_m/coarse_voxel_size_m: expected 0 < voxel_size_m <= "
                f"coarse_voxel_size_m, got {self.voxel_size_m} and {self.coarse_voxel_size_m}"
            )


@dataclass(frozen=True)
class Observations:
    """One frame's data for the tracker.

    Attributes
    ----------
    points : (N, 3) float64
        World points, metres; N may be 0.
    normals : (N, 3) float64
        Unit outward surface normals at the points.
    """

    points: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(self.normals, dtype=np.float64).reshape(-1, 3)
        if points.shape != normals.shape:
            raise ValueError(f"observations: {len(points)} points but {len(normals)} normals")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "normals", normals)

    def __len__(self) -> int:
        return len(self.points)


def check_tolerated_views(tolerated_views: int, n_cameras: int) -> None:
    """Refuse a `ReconstructionParams.tolerated_views` that leaves fewer than two views to agree on a point: the
    hull would then hold what a single camera sees, its whole viewing cone.

    Raises
    ------
    InputError
        Naming the parameter, the rig's camera count and the largest tolerance it allows.
    """
    if tolerated_views > n_cameras - 2:
        raise InputError(f"reconstruction.tolerated_views={tolerated_views}: the rig has {n_cameras} cameras "
                         f"(expected at most {max(n_cameras - 2, 0)}: at least two views must agree on every point)")


def reconstruct(masks: Sequence[np.ndarray], rig: Rig, volume, params: ReconstructionParams,
                hidden: Sequence[np.ndarray | None] | None = None) -> Observations:
    """Points and outward normals of the person seen in ``masks``, inside the working ``volume``.

    Parameters
    ----------
    masks : sequence of (H, W) uint8
        One silhouette per camera of ``rig``, in rig order, each the camera's image size; 0 = background.
    rig : Rig
    volume : (2, 3) float
        Working volume ``[min, max]`` corners, metres; points outside it are dropped.
    params : ReconstructionParams
    hidden : sequence of (H, W) uint8 or None, optional
        Per camera, the part of its image hidden behind something in front of the subject (nonzero), found by
        :func:`~stages.reconstruction.occlusion.hidden_parts`: the view does not carve there. None: nothing hidden.

    Returns
    -------
    Observations
        At most ``params.n_observations`` points, unit normals, no NaN; empty when the silhouettes do
        not agree on anything (every view empty, the person outside the volume, or a view whose image shows
        background where the others place him).
    """
    volume = np.asarray(volume, dtype=np.float64)
    if volume.shape != (2, 3) or not np.all(np.isfinite(volume)) or not np.all(volume[1] > volume[0]):
        raise InputError(
            f"volume: expected finite [min, max] corners of shape (2, 3), min < max, got {volume.tolist()}"
        )
    if len(masks) != len(rig):
        raise InputError(f"masks: expected one mask per camera ({len(rig)}), got {len(masks)}")
    checked = []
    for camera, mask in zip(rig, masks, strict=True):
        mask = np.asarray(mask)
        width, height = camera.size
        if mask.shape != (height, width):
            raise InputError(
                f"mask of camera '{camera.name}': expected shape ({height}, {width}) from the camera's image "
                f"size, got {mask.shape}"
            )
        checked.append(np.where(mask > 0, np.uint8(255), np.uint8(0)) if mask.dtype != np.uint8 else mask)
    hidden = [None] * len(rig) if hidden is None else list(hidden)
    if len(hidden) != len(rig) or any(part is not None and part.shape != mask.shape
                                      for part, mask in zip(hidden, checked, strict=True)):
        raise InputError(f"hidden: expected one map per camera ({len(rig)}) of its silhouette's shape, or None")
    if params.method == "visual_hull":
        points, normals = hull_surface_points(
            [mask if part is None else cv2.bitwise_or(mask, part) for mask, part in zip(checked, hidden, strict=True)],
            rig, volume,
            n_observations=params.n_observations,
            tolerated_views=params.tolerated_views,
            voxel_size_m=params.voxel_size_m,
            coarse_voxel_size_m=params.coarse_voxel_size_m,
        )
    else:
        points, normals = rim_points(
            checked, rig, volume,
            n_observations=params.n_observations,
            tolerated_views=params.tolerated_views,
            rim_placement=params.rim_placement,
            samples_per_ray=params.samples_per_ray,
            contour_smoothing_px=params.contour_smoothing_px,
            hidden=hidden,
        )
    return Observations(*usable_observations(points, normals))


#: How far from 1 an observation's normal length may be: float32 rounding on disk is far below it, and a
#: reader of the observations (``pipeline.io.frames_io.read_ply``) refuses more.
UNIT_NORMAL_TOLERANCE = 1e-3


def usable_observations(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``points`` and ``normals`` (N, 3) that are finite and whose normal has unit length.

    A cone face seen edge-on (contour tangent along the ray) has no normal; its zero vector would be read
    back as a damaged file and means nothing to the tracker, so such a point is not an observation.
    """
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    keep = (np.all(np.isfinite(points), axis=1) & np.isfinite(length)
            & (np.abs(length - 1.0) <= UNIT_NORMAL_TOLERANCE))
    return points[keep], normals[keep]
