"""Rendering a posed body in a textured room, as a calibrated camera sees it.

Every pixel is one ray through the pixel centre (through the lens distortion, via
``Camera.pixel_rays``). The room is a box (planked floor, walls with skirting, doors and pictures,
ceiling) intersected analytically, rendered once per camera: it is also the clean plate. The body is
ray-cast per frame with open3d's ``RaycastingScene``, only inside the bounding box of its projection.

Light is computed in linear units, as a studio lights a room: a key light high on one side, a weaker fill
light from the other side and an ambient term for the light bounced by walls, floor and ceiling (stronger
from above than from below), each surface reflecting it with Lambert's law (no cast shadows). Room and
body share this model, so a surface turned away from the key light is dimmer but never black. Colours are
chosen as sRGB (how they look on a screen) and converted to linear albedos.

The camera then does what a real one does: each camera's exposure is metered once on the empty room and
locked (mid-grey at 18 % linear, as a light meter does), the lens blurs a little and darkens the corners
(vignetting), a tone curve maps linear light to 8-bit sRGB with a soft shoulder (highlights roll off
instead of clipping), and Gaussian sensor noise is added. The true mask is the set of pixels whose centre
ray hits the body.

Clothing takes one colour per material: the shirt is a light grey-blue close to the cool walls, the shoes
close to the skirting boards, so background subtraction meets real (partial) camouflage.

Colours are RGB floats until ``finish_image`` (which returns OpenCV's BGR channel order for writing).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from scipy import ndimage

from calib.camera import Camera
from pipeline.lab.synth.posed import MATERIALS, PosedBody

# Clothing and skin, sRGB, in MATERIALS order.
CLOTHING_COLOURS = {
    "skin": (0.80, 0.60, 0.48),
    "shirt": (0.68, 0.72, 0.76),  # close to the cool walls: silhouettes get holes against them
    "trousers": (0.17, 0.19, 0.27),
    "shoes": (0.09, 0.09, 0.09),  # close to the skirting boards
    "hair": (0.17, 0.11, 0.07),
}
# Room surfaces, sRGB; walls in the order +x, -x, +y, -y.
WALL_COLOURS = ((0.80, 0.76, 0.67), (0.74, 0.76, 0.72), (0.82, 0.78, 0.70), (0.70, 0.72, 0.74))
FLOOR_COLOUR = (0.40, 0.36, 0.33)  # a grey-stained oak studio floor: not the hue of skin
SKIRTING_COLOUR = (0.11, 0.10, 0.10)
CEILING_COLOUR = (0.88, 0.88, 0.86)


@dataclass(frozen=True)
class Light:
    """A distant light: the direction towards it (world, need not be unit) and its irradiance."""

    direction: tuple[float, float, float]
    intensity: float


#: The studio lights: a key light high on one side and a fill light, half as strong, from the other side
#: (the usual 2:1 key-to-fill ratio of a lit set).
LIGHTS = (Light((0.4, -0.5, 1.0), 0.8), Light((-0.6, 0.7, 0.5), 0.4))
#: Irradiance bounced by the room onto a surface facing up; a surface facing the floor gets
#: ``AMBIENT_FROM_BELOW`` of it (the ceiling is lit and pale, the floor darker).
AMBIENT = 0.3
AMBIENT_FROM_BELOW = 0.6
#: Inward normals of the room's surfaces, in the order of ``_room_colours``: walls +x, -x, +y, -y, floor,
#: ceiling.
ROOM_NORMALS = np.array([(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, 1), (0, 0, -1)], dtype=float)
#: Exposure: the median luminance of the empty room is metered to this linear value, a little above the
#: 18 % grey a light meter assumes, so that images average near the middle of the 8-bit range (level 124
#: after the sRGB curve) with headroom for highlights.
METERED_GREY = 0.2
#: Rec. 709 luminance weights of linear RGB.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: Linear exposure above which the tone curve rolls off smoothly towards white instead of clipping.
SHOULDER = 0.8
#: Optical blur of the whole image (Gaussian sigma, pixels).
LENS_BLUR_PX = 0.6
#: Rays per pixel along each axis for the (static) room.
ROOM_SUPERSAMPLING = 2
#: Pixels added around the body's projected bounding box before ray casting.
BOX_MARGIN_PX = 3


@dataclass(frozen=True)
class Room:
    """An axis-aligned box room, metres, floor at z = 0.

    Parameters
    ----------
    centre : (2,) float
        Floor centre (x, y).
    half_size : (2,) float
        Half the room's extent along x and y.
    height : float
        Ceiling height.
    seed : int
        Seeds the textures (planks, wall stains, pictures), so every camera sees the same room.
    """

    centre: tuple[float, float]
    half_size: tuple[float, float]
    height: float
    seed: int


def pixel_grid_rays(camera: Camera) -> np.ndarray:
    """(H, W, 3) float32 unit world directions of the rays through every pixel centre."""
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    rays = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]))
    return rays.reshape(height, width, 3).astype(np.float32)


def _value_noise(u: np.ndarray, v: np.ndarray, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise in [-1, 1] at surface coordinates ``u``, ``v`` (metres), features about ``scale`` m."""
    grid = rng.uniform(-1.0, 1.0, (64, 64))
    coordinates = np.stack([u.ravel() / scale, v.ravel() / scale])
    return ndimage.map_coordinates(grid, coordinates, order=3, mode="grid-wrap").reshape(u.shape)


def render_room(camera: Camera, rays: np.ndarray, room: Room) -> np.ndarray:
    """(H, W, 3) linear RGB radiance of the empty room seen by ``camera`` (the clean plate, before the camera).

    Rendered with ``ROOM_SUPERSAMPLING`` x ``ROOM_SUPERSAMPLING`` rays per pixel (the pixel rays
    interpolated bilinearly: they vary smoothly) and averaged, so plank seams do not alias.
    """
    height, width = rays.shape[:2]
    s = ROOM_SUPERSAMPLING
    fine = cv2.resize(rays, (width * s, height * s), interpolation=cv2.INTER_LINEAR)  # sub-pixel centres
    fine /= np.linalg.norm(fine, axis=2, keepdims=True)
    image = _room_colours(camera, fine, room)
    return cv2.resize(image.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)


def _room_colours(camera: Camera, rays: np.ndarray, room: Room) -> np.ndarray:
    """(H, W, 3) linear RGB radiance of the room surfaces hit by ``rays`` (H, W, 3) from the camera centre."""
    rng = np.random.default_rng(room.seed)
    centre = camera.centre
    d = rays.reshape(-1, 3).astype(np.float64)
    cx, cy = room.centre
    hx, hy = room.half_size
    # Distance to each of the six planes along every ray; the camera is inside the box.
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = np.stack(
            [
                (cx + hx - centre[0]) / d[:, 0],
                (cx - hx - centre[0]) / d[:, 0],
                (cy + hy - centre[1]) / d[:, 1],
                (cy - hy - centre[1]) / d[:, 1],
                (0.0 - centre[2]) / d[:, 2],
                (room.height - centre[2]) / d[:, 2],
            ]
        )  # (6, N)
    candidates = np.where(candidates > 0, candidates, np.inf)
    surface = np.argmin(candidates, axis=0)  # 0..3 walls (+x, -x, +y, -y), 4 floor, 5 ceiling
    hit = centre + np.min(candidates, axis=0)[:, None] * d
    colour = np.zeros_like(hit)  # (N, 3) sRGB albedo

    floor = surface == 4
    x, y = hit[floor, 0], hit[floor, 1]
    plank_width = 0.18
    plank = np.floor(x / plank_width)
    plank_tone = rng.uniform(0.8, 1.15, 512)[plank.astype(int) % 512]
    grain = 0.06 * np.sin(2 * np.pi * (y * 3.0 + 7.0 * _value_noise(x, y, 0.35, rng)))
    joint_offset = rng.uniform(0, 2.5, 512)[plank.astype(int) % 512]
    seam = (np.abs(x / plank_width - np.round(x / plank_width)) * plank_width < 0.004) | (
        np.abs(((y + joint_offset) % 2.5) - 1.25) > 1.245
    )
    floor_colour = np.asarray(FLOOR_COLOUR) * (plank_tone + grain)[:, None]
    floor_colour[seam] *= 0.55
    colour[floor] = floor_colour

    for wall in range(4):
        on_wall = surface == wall
        along = hit[on_wall, 1] if wall < 2 else hit[on_wall, 0]
        z = hit[on_wall, 2]
        base = np.asarray(WALL_COLOURS[wall])
        stain = 0.05 * _value_noise(along, z, 0.6, rng) + 0.02 * _value_noise(along, z, 0.08, rng)
        wall_colour = base * (1.0 + stain)[:, None]
        wall_colour = _wall_features(wall_colour, along, z, rng, room)
        wall_colour[z < 0.12] = SKIRTING_COLOUR
        colour[on_wall] = wall_colour

    colour[surface == 5] = CEILING_COLOUR
    shade = irradiance(ROOM_NORMALS)[surface]  # (N,) every surface is a plane: one irradiance each
    return (srgb_to_linear(colour) * shade[:, None]).reshape(rays.shape)


def _wall_features(colour: np.ndarray, along: np.ndarray, z: np.ndarray, rng, room: Room) -> np.ndarray:
    """Doors, pictures and a dado rail painted onto a wall's colours (N, 3) at (along, z) metres."""
    colour = colour.copy()
    extent = max(room.half_size)
    rail = np.abs(z - 0.95) < 0.02
    colour[rail] = colour[rail] * 0.7
    for _ in range(3):
        left = rng.uniform(-extent, extent - 1.0)
        if rng.random() < 0.35:  # a door
            inside = (along > left) & (along < left + 0.9) & (z < 2.05)
            colour[inside] = rng.choice([(0.55, 0.42, 0.30), (0.90, 0.90, 0.88), (0.35, 0.38, 0.42)])
        else:  # a picture with a frame
            width, height = rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.8)
            bottom = rng.uniform(1.2, 1.7)
            inside = (along > left) & (along < left + width) & (z > bottom) & (z < bottom + height)
            border = inside & ~(
                (along > left + 0.03)
                & (along < left + width - 0.03)
                & (z > bottom + 0.03)
                & (z < bottom + height - 0.03)
            )
            tint = rng.uniform(0.15, 0.9, 3)
            pattern = 0.5 + 0.5 * np.sin(along[inside] * rng.uniform(6, 20) + z[inside] * rng.uniform(4, 15))
            colour[inside] = tint * (0.6 + 0.4 * pattern)[:, None]
            colour[border] = (0.12, 0.10, 0.08)
    return colour


def irradiance(normals: np.ndarray) -> np.ndarray:
    """(N,) Light received by surfaces with unit normals (N, 3): hemispherical ambient plus Lambert lights.

    The ambient term blends from ``AMBIENT`` facing up to ``AMBIENT * AMBIENT_FROM_BELOW`` facing down
    (a hemisphere light); each of ``LIGHTS`` adds its intensity times the cosine of incidence.
    """
    up = normals[:, 2]
    ambient = AMBIENT * (AMBIENT_FROM_BELOW + (1.0 - AMBIENT_FROM_BELOW) * (1.0 + up) / 2.0)
    direct = sum(
        light.intensity * np.clip(normals @ (np.asarray(light.direction) / np.linalg.norm(light.direction)), 0, None)
        for light in LIGHTS
    )
    return ambient + direct


def srgb_to_linear(colour: np.ndarray) -> np.ndarray:
    """Linear values of sRGB-encoded colours in [0, 1] (IEC 61966-2-1)."""
    colour = np.asarray(colour, dtype=float)
    return np.where(colour <= 0.04045, colour / 12.92, ((colour + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(value: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values in [0, 1] (IEC 61966-2-1), same dtype as the input."""
    return np.where(value <= 0.0031308, 12.92 * value, 1.055 * np.power(np.maximum(value, 0.0031308), 1 / 2.4) - 0.055)


def _vignetting(camera: Camera) -> np.ndarray:
    """(H, W) Brightness falloff towards the image corners (cos^4 law, softened)."""
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width) - camera.K[0, 2], np.arange(height) - camera.K[1, 2])
    cos_angle = camera.K[0, 0] / np.sqrt(camera.K[0, 0] ** 2 + u**2 + v**2)
    return 0.6 + 0.4 * cos_angle**4


@dataclass(frozen=True, eq=False)
class BodyLayer:
    """What one camera sees of the body: colours where it is hit, and the hit mask."""

    colour: np.ndarray  # (H, W, 3) RGB, valid where mask
    mask: np.ndarray  # (H, W) bool


def body_scene(posed: PosedBody) -> o3d.t.geometry.RaycastingScene:
    """An open3d ray-casting scene holding the posed body's triangles."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(posed.vertices.astype(np.float32)), o3d.core.Tensor(posed.triangles.astype(np.uint32))
    )
    return scene


def render_body(
    camera: Camera,
    rays: np.ndarray,
    scene: o3d.t.geometry.RaycastingScene,
    posed: PosedBody,
    colours: np.ndarray,
) -> BodyLayer:
    """Ray-cast the posed body from ``camera`` (pixel rays (H, W, 3)) and shade it.

    ``colours`` (len(MATERIALS), 3) are the sRGB albedos of the materials; the layer's colours are linear
    radiance.
    """
    width, height = camera.size
    mask = np.zeros((height, width), dtype=bool)
    image = np.zeros((height, width, 3))
    in_front = camera.depth(posed.vertices) > 0
    if not np.any(in_front):
        return BodyLayer(image, mask)
    uv = camera.project(posed.vertices[in_front])
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - BOX_MARGIN_PX
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + BOX_MARGIN_PX
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width - 1), min(v1, height - 1)
    if u1 < u0 or v1 < v0:
        return BodyLayer(image, mask)
    box_rays = rays[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3)
    origins = np.broadcast_to(camera.centre.astype(np.float32), box_rays.shape)
    result = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(np.concatenate([origins, box_rays], axis=1))))
    hit = np.isfinite(result["t_hit"].numpy())
    triangles = result["primitive_ids"].numpy()[hit]
    barycentric = result["primitive_uvs"].numpy()[hit].astype(np.float64)  # weights of corners 1 and 2
    weights = np.column_stack([1.0 - barycentric.sum(axis=1), barycentric])  # (n, 3)
    corners = posed.triangles[triangles]  # (n, 3)
    normals = np.einsum("nk,nkd->nd", weights, posed.vertex_normals[corners])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    view = box_rays[hit].astype(np.float64)
    normals = np.where((np.einsum("nd,nd->n", normals, view) > 0)[:, None], -normals, normals)  # inner side
    materials = posed.vertex_materials[corners[np.arange(len(corners)), np.argmax(weights, axis=1)]]
    facing = 0.85 + 0.15 * np.clip(-np.einsum("nd,nd->n", normals, view), 0.0, 1.0)  # soft rim darkening
    shaded = srgb_to_linear(colours[materials]) * (irradiance(normals) * facing)[:, None]

    box_mask = hit.reshape(v1 - v0 + 1, u1 - u0 + 1)
    mask[v0 : v1 + 1, u0 : u1 + 1] = box_mask
    box_image = np.zeros((v1 - v0 + 1, u1 - u0 + 1, 3))
    box_image[box_mask] = shaded
    image[v0 : v1 + 1, u0 : u1 + 1] = box_image
    return BodyLayer(image, mask)


def clothing_colours(rng: np.random.Generator) -> np.ndarray:
    """(len(MATERIALS), 3) sRGB albedos: the standard outfit, each colour jittered by a few percent."""
    base = np.array([CLOTHING_COLOURS[name] for name in MATERIALS])
    return np.clip(base * rng.uniform(0.94, 1.06, base.shape), 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class Exposure:
    """One camera's locked exposure: linear gain per pixel (exposure times the lens's vignetting)."""

    gain: np.ndarray  # (H, W) float32


def meter_exposure(camera: Camera, plate: np.ndarray) -> Exposure:
    """The exposure that brings the median luminance of the empty room ``plate`` (H, W, 3) to ``METERED_GREY``.

    Metered once per camera on the clean plate and then kept for every frame, as a studio locks its
    cameras' exposure: the person entering the view does not change the background's levels.
    """
    vignetting = _vignetting(camera)
    luminance = (plate @ LUMINANCE) * vignetting
    gain = METERED_GREY / max(float(np.median(luminance)), 1e-6)
    return Exposure((gain * vignetting).astype(np.float32))


def tone_curve(value: np.ndarray) -> np.ndarray:
    """8-bit-ready display values in [0, 1] of exposed linear values: a soft shoulder, then sRGB.

    Above ``SHOULDER`` the value is compressed by a tanh that joins the identity with equal slope and
    tends to 1, so highlights (the pale ceiling, a lit white door) roll off instead of clipping flat.
    """
    span = 1.0 - SHOULDER
    rolled = SHOULDER + span * np.tanh((value - SHOULDER) / span)
    return linear_to_srgb(np.clip(np.where(value > SHOULDER, rolled, value), 0.0, 1.0))


def finish_image(
    radiance: np.ndarray, exposure: Exposure, noise_sigma: float, rng: np.random.Generator
) -> np.ndarray:
    """(H, W, 3) uint8 BGR of linear ``radiance`` (H, W, 3) RGB, as the camera records it.

    Exposure and vignetting, lens blur (in linear light, where optics acts), the tone curve, then
    Gaussian sensor noise of ``noise_sigma`` grey levels.
    """
    exposed = radiance.astype(np.float32) * exposure.gain[:, :, None]
    image = tone_curve(cv2.GaussianBlur(exposed, (0, 0), LENS_BLUR_PX)).astype(np.float32) * 255.0
    if noise_sigma > 0:
        image = image + rng.normal(0.0, noise_sigma, image.shape).astype(np.float32)
    return cv2.cvtColor(np.clip(np.rint(image), 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
