"""A test studio for the floor test of shadows: a ring of cameras, a plain floor (z = 0) under a grey wall, a person
standing at the origin as a vertical cylinder, and the person's soft contact shadow on the floor around the feet,
rendered by ray casting with Gaussian sensor noise.
"""

from __future__ import annotations

import numpy as np

from calib.camera import Camera

HEIGHT, WIDTH = 290, 390
FLOOR, WALL = np.array([80.0, 110.0, 140.0]), np.array([150.0, 150.0, 150.0])  # BGR
PERSON_RADIUS_M, PERSON_HEIGHT_M, SHADOW_RADIUS_M = 0.2, 1.7, 0.6
VOLUME = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.0]])


def ring(count: int) -> list[Camera]:
    """``count`` cameras 3 m from the person, 1.6 m up, looking at his middle."""
    angles = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return [Camera.look_at(f"cam{i}", (3.0 * np.cos(a), 3.0 * np.sin(a), 1.6), (0.0, 0.0, 0.8), f_px=300.0,
                           size=(WIDTH, HEIGHT)) for i, a in enumerate(angles)]


def render(camera: Camera, clothing: np.ndarray | None, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(image, true mask) of the studio by ray casting; ``clothing`` None: the empty studio (the clean plate)."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    rays = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    centre = camera.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        to_floor = -centre[2] / rays[:, 2]
    floor = np.isfinite(to_floor) & (to_floor > 0)
    ground = centre[:2] + np.where(floor, to_floor, 0.0)[:, None] * rays[:, :2]
    image = np.where(floor[:, None], FLOOR, WALL)
    if clothing is None:
        return _noisy(image, rng), np.zeros((HEIGHT, WIDTH), np.uint8)
    radius = np.linalg.norm(ground, axis=1)
    darkening = 0.45 * np.clip(1.0 - radius / SHADOW_RADIUS_M, 0.0, 1.0) ** 0.5  # soft, darkest at the feet
    image = image * (1.0 - np.where(floor, darkening, 0.0))[:, None]
    # Ray and cylinder x² + y² = r²: a s² + b s + c = 0 along the ray, the nearer root, within the height.
    a = (rays[:, :2] ** 2).sum(axis=1)
    b = 2.0 * rays[:, :2] @ centre[:2]
    c = centre[:2] @ centre[:2] - PERSON_RADIUS_M**2
    with np.errstate(invalid="ignore"):
        s = (-b - np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    z = centre[2] + s * rays[:, 2]
    person = np.isfinite(s) & (s > 0) & (z >= 0) & (z <= PERSON_HEIGHT_M)
    image[person] = clothing
    return _noisy(image, rng), (person.reshape(HEIGHT, WIDTH) * 255).astype(np.uint8)


def _noisy(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    noisy = image.reshape(HEIGHT, WIDTH, 3) + rng.normal(0.0, 2.0, (HEIGHT, WIDTH, 3))
    return np.clip(noisy, 0, 255).astype(np.uint8)
