"""Projection-matrix calibrations: a directory with one text file of a 3x4 matrix P per camera.

Many academic multi-view datasets ship their calibration this way: ``x_img ~ P [X_world; 1]``, twelve
numbers row by row, no lens distortion. The camera name is the file name up to its first dot
(``Camera1.Pmat.cal`` is camera ``Camera1``); files are taken in natural order (``Camera10`` after
``Camera9``). P is decomposed on load into ``K [R | t]`` (:func:`decompose`), and the image size, which
the files do not store, comes from the media.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.linalg

from calib import _parse
from calib.camera import Rig
from calib.errors import InputError, NoImageSize
from calib.formats import natural_key

#: Extension the writer gives each camera's file (the name is everything before the first dot).
FILE_SUFFIX = ".P.txt"

# det(M) of the left 3x3 block below this fraction of |M|^3 (cube of the largest singular value) means
# a camera at infinity or a degenerate matrix: no finite centre, no K R to recover.
SINGULAR_RATIO = 1e-12


def decompose(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K (3, 3), R (3, 3), t (3,))`` with ``P ~ K [R | t]``: K upper triangular with positive diagonal
    and ``K[2, 2] = 1`` (skew kept), R a proper rotation.

    P is known only up to a scale of either sign. The left block is ``M = s K R`` with ``det K > 0`` and
    ``det R = +1``, so the sign of ``det M`` is the sign of ``s``; flipping P to make it positive puts the
    points that P sees with positive depth ``w`` in front of the camera (Hartley and Zisserman, 6.2.3).
    The RQ decomposition ``M = K' R'`` (scipy.linalg.rq) is unique up to the signs of K's columns;
    ``D = diag(sign(diag K'))`` makes them positive, ``K = K' D``, ``R = D R'``, and then
    ``det R = sign(det M) = +1``. Finally ``t = K^-1 p_4`` before K is divided by ``K[2, 2] = s``.
    """
    P = P * np.sign(np.linalg.det(P[:, :3]))
    K, R = scipy.linalg.rq(P[:, :3])
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    return K / K[2, 2], R, t


def read_matrix(path: Path) -> np.ndarray:
    """(3, 4) P from a text file of twelve whitespace-separated numbers (row by row)."""
    try:
        words = path.read_text(encoding="utf-8").split()
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file, expected 12 numbers (a 3x4 projection matrix)") from None
    try:
        values = np.array([float(word) for word in words])
    except ValueError:
        bad = next(word for word in words if not _is_float(word))
        raise InputError(f"{path}: {bad[:20]!r} is not a number, expected 12 numbers "
                         "(a 3x4 projection matrix, row by row)") from None
    if len(values) != 12:
        raise InputError(f"{path}: {len(values)} numbers, expected 12 (a 3x4 projection matrix, row by row)")
    if not np.all(np.isfinite(values)):
        raise InputError(f"{path}: contains NaN or infinity, expected 12 finite numbers")
    P = values.reshape(3, 4)
    M = P[:, :3]
    if abs(np.linalg.det(M)) <= SINGULAR_RATIO * np.linalg.norm(M, 2) ** 3:
        raise InputError(f"{path}: the projection matrix is rank-deficient (its left 3x3 block has rank "
                         f"{np.linalg.matrix_rank(M)}), expected P = K [R | t] of a camera with a finite centre")
    return P


def _is_float(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def load(path: Path, image_sizes: dict[str, tuple[int, int]], keep: set[str] | None = None) -> Rig:
    """The rig of the directory ``path``: every visible file is one camera's P (only those named in ``keep``;
    None: all)."""
    if not path.is_dir():
        raise InputError(f"{path}: no such directory, expected a folder of 3x4 projection matrices "
                         "(one text file per camera)")
    files = sorted((p for p in path.iterdir() if p.is_file() and not p.name.startswith(".")),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise InputError(f"{path}: no projection matrix files, expected one text file per camera")
    cameras = []
    for file in files:
        name = file.name.split(".")[0]
        if keep is not None and name not in keep:
            continue
        if name not in image_sizes:
            raise NoImageSize(f"{file}: no image size for camera {name!r}, expected it from the camera's "
                             "video or images")
        K, R, t = decompose(read_matrix(file))
        cameras.append(_parse.camera(str(file), name=name, K=K, dist=np.zeros(5), R=R, t=t,
                                     size=image_sizes[name]))
    return _parse.rig(str(path), cameras)


def save(rig: Rig, path: Path) -> None:
    """Write one ``<name>.P.txt`` per camera into the directory ``path``: ``K [R | t]``, three rows of four."""
    for camera in rig:
        if "." in camera.name or not camera.name.strip() or "/" in camera.name:
            raise InputError(f"camera name {camera.name!r}: cannot be a projection file's name up to its "
                             "first dot, expected a name without '.' or '/'")
        if np.any(camera.dist):
            raise InputError(f"camera {camera.name!r}: has lens distortion {camera.dist.tolist()}, which a "
                             "projection matrix cannot hold; expected no distortion")
    path.mkdir(parents=True, exist_ok=True)
    for camera in rig:
        rows = "\n".join(" ".join(repr(float(value)) for value in row) for row in camera.P)
        (path / f"{camera.name}{FILE_SUFFIX}").write_text(rows + "\n", encoding="utf-8")

