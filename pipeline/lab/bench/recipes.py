"""Synthetic captures of the benchmark: their recipes, and a cache that renders each one only once.

A recipe is a name plus the :class:`~pipeline.lab.synth.writer.SynthParams` that make the capture, with the clip
given relative to the mocap folders (``clips/135_04.amc``) so that the recipe, and its hash, do not depend
on where the repository lives, plus the generator's version (a hash of the synth and mocap sources): a
changed renderer makes a different capture from the same parameters.

:func:`ensure_capture` keeps ``<root>/<name>/`` and writes the recipe next to it as
``<root>/<name>.recipe.json`` once the capture is complete; the capture is rendered again only when the
recipe's hash changes (or a previous rendering was interrupted, which leaves no recipe file).
"""

from __future__ import annotations

import functools
import hashlib
import json
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.lab.poselib import clip_path
from pipeline.lab.synth.writer import SynthParams, synthesise

#: Clip files (relative to the mocap folders) and the ASF skeleton of each AMC clip.
CLIPS: dict[str, tuple[str, str | None]] = {
    "135_04": ("clips/135_04.amc", "clips/martialwalk.asf"),
    "135_07": ("clips/135_07.amc", "clips/martialwalk.asf"),
    "131_05": ("clips/131_05.amc", "clips/mjackson.asf"),
    "md_walk": ("clips/md_walk.amc", "clips/moderndance.asf"),
    "09_01": ("clips/09_01.bvh", None),
}
RECIPE_SUFFIX = ".recipe.json"
#: Sources that decide what a recipe renders (the generator's version).
GENERATOR_SOURCES = ("synth/*.py", "mocap/*.py")


@functools.cache
def generator_version() -> str:
    """SHA-256 (hex, 12 digits) of the generator's source files."""
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for path in sorted(p for pattern in GENERATOR_SOURCES for p in package.glob(pattern)):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


@dataclass(frozen=True)
class Recipe:
    """One synthetic capture: a clip (key of :data:`CLIPS`) and how it is filmed.

    ``options`` are the remaining :class:`SynthParams` fields (body, n_cameras, size, noise_sigma, ...);
    ``quick_seconds`` replaces ``seconds`` for a ``--quick`` run (the capture then gets its own name).
    """

    name: str
    clip: str
    start_s: float
    seconds: float | None
    options: tuple[tuple[str, object], ...] = ()
    quick_seconds: float | None = 0.5

    def quick(self) -> Recipe:
        """The short version of this recipe used by ``--quick`` (a separate capture)."""
        return replace(self, name=f"{self.name}-quick", seconds=self.quick_seconds)

    def spec(self) -> dict:
        """Plain-data description: what is hashed and stored next to the capture."""
        clip, skeleton = CLIPS[self.clip]
        return {"name": self.name, "clip": clip, "skeleton": skeleton, "start_s": self.start_s,
                "seconds": self.seconds, **dict(self.options), "generator": generator_version()}

    def synth_params(self) -> SynthParams:
        """The generator's parameters, clip paths resolved in this checkout."""
        clip, skeleton = CLIPS[self.clip]
        return SynthParams(clip=str(clip_path(clip)), skeleton=None if skeleton is None else str(clip_path(skeleton)),
                           start_s=self.start_s, seconds=self.seconds, **dict(self.options))

    def option(self, key: str):
        """An option's value, falling back to the generator's default."""
        return dict(self.options).get(key, getattr(SynthParams(clip=""), key))


def recipe_hash(spec: dict) -> str:
    """SHA-256 (hex, 16 digits) of the canonical JSON of a recipe's spec: key order does not matter."""
    text = json.dumps(spec, sort_keys=True, separators=(",", ":"), default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def recipe_file(root: Path, name: str) -> Path:
    return Path(root) / f"{name}{RECIPE_SUFFIX}"


def is_current(root: Path, recipe: Recipe) -> bool:
    """Whether ``<root>/<name>/`` holds a complete capture made from exactly this recipe."""
    path = recipe_file(root, recipe.name)
    if not path.is_file() or not (Path(root) / recipe.name / "capture.yaml").is_file():
        return False
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(stored, dict) and stored.get("hash") == recipe_hash(recipe.spec())


def ensure_capture(root: Path, recipe: Recipe) -> Path:
    """The capture directory of ``recipe`` under ``root``, rendered first unless it is current.

    The recipe file is removed before rendering and written after it, so an interrupted rendering is
    never mistaken for a finished one.
    """
    root = Path(root)
    out = root / recipe.name
    if is_current(root, recipe):
        return out
    recipe_file(root, recipe.name).unlink(missing_ok=True)
    shutil.rmtree(out, ignore_errors=True)
    root.mkdir(parents=True, exist_ok=True)
    synthesise(recipe.synth_params(), out)
    spec = recipe.spec()
    recipe_file(root, recipe.name).write_text(json.dumps({"hash": recipe_hash(spec), "recipe": spec}, indent=1,
                                                         default=list) + "\n")
    return out


def describe(recipe: Recipe) -> dict:
    """The facts about a capture a results row shows (clip, body, cameras, size, noise, ...)."""
    width, height = recipe.option("size")
    return {
        "clip": recipe.clip, "body": recipe.option("body"), "cameras": recipe.option("n_cameras"),
        "size": f"{width}x{height}", "noise": recipe.option("noise_sigma"),
        "distractors": recipe.option("distractors"), "media": recipe.option("media"),
        "calibration": f"{recipe.option('calib_format')} {recipe.option('units')} {recipe.option('up')}",
        "height_known": recipe.option("height_known"),
    }


def _opts(**options) -> tuple[tuple[str, object], ...]:
    return tuple(sorted(options.items()))


#: The paper's studio (Horaud et al. 2009, Sec. 4.2): 6 cameras, 780 x 580, 28 frames/s, mp4 video.
#: Taekwondo kicks (135_07), 6 s; the memory check also runs its first third.
SPEED = Recipe("speed-135_07", "135_07", 0.3, 6.0, _opts(n_cameras=6, size=(780, 580), fps=28.0),
               quick_seconds=0.75)

#: Captures the tracker was never tuned on: every row changes several things at once (clip, body, camera
#: count, resolution, sensor noise, distractors, media, calibration format/units/up axis, known height).
UNSEEN: tuple[Recipe, ...] = (
    Recipe("front_kicks", "135_04", 2.6, 3.0, _opts()),
    Recipe("front_kicks_capsules", "135_04", 4.4, 3.0,
           _opts(body="capsules", n_cameras=8, noise_sigma=4.0, distractors=3, calib_format="opencv",
                 units="mm", up="+y", height_known=False, seed=1)),
    Recipe("walk_capsules", "md_walk", 0.5, 3.0,
           _opts(body="capsules", n_cameras=5, size=(640, 480), media="images", calib_format="anipose",
                 units="cm", up="-z", seed=2)),
    Recipe("walk_lowres", "md_walk", 1.5, 3.0,
           _opts(n_cameras=6, size=(480, 360), noise_sigma=6.0, height_known=False, seed=3)),
    # 09_01 is a retarget onto a non-CMU skeleton: the generator dresses it in joint-bound capsules only.
    Recipe("run", "09_01", 0.05, None, _opts(body="capsules", n_cameras=8, calib_format="anipose", up="+y", seed=4)),
    Recipe("run_hires", "09_01", 0.05, None,
           _opts(body="capsules", size=(960, 720), noise_sigma=3.0, distractors=2, media="images",
                 calib_format="opencv", units="cm", up="+x", height_known=False, seed=5)),
    Recipe("taekwondo", "135_07", 5.8, 3.0,
           _opts(noise_sigma=3.0, distractors=4, calib_format="opencv", height_known=False, seed=6)),
    Recipe("taekwondo_capsules", "135_07", 0.5, 3.0,
           _opts(body="capsules", n_cameras=5, units="mm", up="-y", seed=7)),
    Recipe("leaning", "131_05", 5.0, 3.0,
           _opts(n_cameras=8, size=(640, 480), calib_format="anipose", units="mm", seed=8)),
    Recipe("leaning_capsules_noisy", "131_05", 5.8, 3.0,
           _opts(body="capsules", noise_sigma=8.0, distractors=6, units="cm", up="+y", height_known=False,
                 seed=9)),
)
#: The subset a ``--quick`` run renders (short versions): one per body and per calibration format.
QUICK_UNSEEN = ("front_kicks", "walk_capsules", "leaning")

#: The paper's simulation (Sec. 4.1): seven cameras; rendered at 56 frames/s so that 28, 14 and 7 frames/s
#: are exact subsamples of it. Front kicks (135_04): the knee flexes through its whole range.
PAPER = Recipe("paper-135_04", "135_04", 2.6, 3.6, _opts(n_cameras=7, fps=56.0), quick_seconds=0.4)
