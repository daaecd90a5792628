"""Shared helpers for the tracking tests: data sampled on the body's own ellipsoids."""

import numpy as np

from stages.tracking.body import sample_surface

VOLUME = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.3]])


def sample_ellipsoids(body, pose, count, rng, *, outlier_fraction=0.0):
    """Points and outward normals on the posed ellipsoids (`sample_surface`), plus outliers.

    Outliers are uniform in VOLUME with random unit normals; they make up `outlier_fraction` of the
    returned data.
    """
    y, n = sample_surface(body, pose, count, rng)
    n_out = int(round(count * outlier_fraction / (1.0 - outlier_fraction)))
    y_out = rng.uniform(VOLUME[0], VOLUME[1], (n_out, 3))
    n_rand = rng.normal(size=(n_out, 3))
    n_rand /= np.linalg.norm(n_rand, axis=1, keepdims=True)
    return np.vstack([y, y_out]), np.vstack([n, n_rand])


def random_pose(body, rng, scale=0.3):
    """A random joint configuration inside the limits, standing at the origin, turned by 0.5 rad."""
    pose = body.zero_pose()
    pose[3] = 0.5
    pose[6:] += rng.normal(0.0, scale, body.pose_size - 6)
    return body.clip(pose)


def data_near_a_pose(body, seed, count, spread=0.05):
    """Data (20 % outliers) sampled at a random pose, and a pose about `spread` rad away from it: every
    pair is then a little off, as between EM iterations. Returns y, n, pose, rng."""
    rng = np.random.default_rng(seed)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, count, rng, outlier_fraction=0.2)
    return y, n, truth + rng.normal(0.0, spread, body.pose_size), rng
