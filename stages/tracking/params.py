"""The tracker's parameters: the names a user sets (`--set tracking.<name>=...`), mapped to the algorithm's.

`TrackerParams` is what the tracking stage takes, one flat record of the names users and their
configuration files know; what each part of the tracker runs on is nested in it, built from those
names in this one place: the EM's parameters (`em`, `em.EMParams`), the initialisation's (`init`,
`init.InitParams`) and the limb recovery's (`limbs`, `limbs.LimbParams`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from stages.checks import check_choice, check_int, check_number
from stages.joints import SUBJECT_HEIGHT_RANGE_M
from stages.tracking.body import BodyModel
from stages.tracking.body_file import is_body_path, load_body
from stages.tracking.distances import DISTANCES
from stages.tracking.em import EMParams
from stages.tracking.init import InitParams
from stages.tracking.limbs import LIMB_MIN_OBSERVATIONS, LIMB_SHARE_RATIO, LimbParams


@dataclass(frozen=True)
class TrackerParams:
    """Tunables of the tracker (defaults are generic, not tuned to one sequence).

    Attributes
    ----------
    height_m : float or None
        Subject's stated standing height in metres; None = the data's estimate alone.
    stated_height_weight : float
        Weight, from 0 to 1, of a stated height against the height the first frames' data give (the
        body is sized at stated^w × measured^(1 − w)); 1 takes the stated height as it is and measures
        nothing. Why not 1: a stature fixes the joints only through the body file's proportions, and two
        renderers of one CMU skeleton disagree on its stature by 3-4 %, about as far as the data's own
        estimate errs on bodies of unusual proportions; two estimates with errors of the same size are best averaged.
        Measured in docs/results_by_hand.md ("A stated height weighed against the data's").
    distance : {"normals", "points", "algebraic"}
        Datum-to-ellipsoid distance (the paper's is "normals").
    max_iterations : int
        EM iterations per frame at most.
    tolerance : float
        EM stops when the log-likelihood gain per observation is below this (nats).
    displacement_m : float
        EM stops when no joint centre moved more than this in an iteration (metres).
    estimate_lengths : tuple of str
        Length groups of the body (its file's `lengths`) whose factors are estimated over the first
        `scale_frames` frames, with a prior towards the file's proportions; the others keep the file's
        values, () estimates none. Why these defaults: docs/method.md, "Body dimensions".
    sigma_m : float
        Prediction error (metres, > 0): every frame's EM starts from the previous frame's Σ + σ² I, the
        first from σ² I.
    min_observations : int
        Fewer observations than this: the frame is predicted, not fitted.
    max_outlier_fraction : float
        A fit explaining more than this fraction of the data as outliers is a failure.
    reinit_every : int
        Every this many tracked frames a re-initialisation is tried as well, and the better fit (by
        likelihood) kept: EM can settle in a wrong local optimum (a knee bent the wrong way, legs
        swapped) that passes every check, and a fresh look bounds how long it lasts; 0 never.
    reinit_margin : float
        Such a periodic re-initialisation replaces a fit that passed the checks only when its
        log-likelihood per observation is higher by this much (nats): two fits in nearly the same
        place differ by hundredths, a fit in a different, better optimum by tenths.
    failure_sigma_m : float
        A fit whose Σ has a standard deviation above this (metres) is a failure: the ellipsoids are
        off the body surface by a few centimetres, not by a spread close to the `max_sigma_m` ceiling
        (which it must be below: Σ never grows past that ceiling, so the check would never fail). A tracked
        fit on data whose good fits are wider is held to their usual spread instead
        (`results.spread_limit`), and fails it only when it also explains its data `refit_drop` worse than
        usual; an initialisation is always held to this.
    refit_drop, refit_iterations : float, int
        A fit whose log-likelihood per observation is `refit_drop` nats below the running level gets up
        to `refit_iterations` (at least 1) more EM iterations with a strict stopping rule before it is
        judged, and after its limb recovery the legs exchanged (`limbs.swap_limbs`); inf never refits.
    restart_drop : float
        When such a fit is still `restart_drop` nats below the level, EM also runs from the last pose
        (no velocity) and the better fit is kept (inf never restarts): a motion that stops or turns
        makes the constant-velocity prediction overshoot into another optimum (a chambered kick's knee
        folded sideways).
    velocity_decay : float
        Factor on the velocity for each predicted frame (a gap's motion slows down).
    max_predicted_frames : int
        After this many frames without a fit, the subject is lost and the next data re-initialise.
    scale_frames : int
        Frames over which the height (when unknown: by the initialisations among them) and the length
        factors keep being estimated. A frame's estimate of a length depends on its pose (a forearm held
        towards a camera, an arm against the trunk), and the mean over more of a motion's poses depends on it
        less, while every such frame costs a second EM fit; why 20: docs/results_by_hand.md, "Lengths learnt
        over twenty frames".
    init_headings, init_refine : int
        Initialisation: headings per library pose, hypotheses refined by EM.
    normal_noise_deg : float
        Angular noise of the observed normals (degrees; silhouette normals are off by ~10°): with the
        "normals" distance each pair's covariance grows by how far that tilt slides the ellipsoid point
        of eq. (4) (`EMParams.normal_noise_rad`); 0 is the paper's model.
    min_outlier_prior : float
        Lower bound on the outlier class's prior π_{P+1} (`EMParams.min_outlier_prior`); 0 is the paper's,
        0.5 the most (the outlier class may not own most of the data).
    max_sigma_m : float
        Upper bound on Σ's standard deviations, metres (`EMParams.max_sigma_m`).
    limb_share_ratio, limb_min_observations : float, int
        After every fit, a limb with a segment explaining fewer data than `limb_share_ratio` times
        what its mirror segment explains, or than its running level over the tracked frames (when
        that reference is at least `limb_min_observations`), or that has just folded onto itself, is
        re-initialised locally (`limbs.misplaced_limbs`, `limbs.deserted_limbs`, `limbs.folded_limbs`,
        `limbs.reinitialise_limb`); 0 disables the whole limb recovery.
    limb_check_every : int
        Every this many tracked frames each limb is also searched (`limbs.reinitialise_limb`) when no test
        suspects it, the limbs in turn (`limbs.checks_due`): a limb can settle a few centimetres off in a
        place where it explains about its usual share of the data (a planted foot's shank), and the likelihood
        level, learnt from the same track, soon takes the lower likelihood for usual, so no test ever fires;
        0 never. Why 48 (at 28 frames/s, each limb every 1.7 s): docs/results_by_hand.md, "Every limb checked
        half as often".
    seed : int
        Seed of the random subsamples on which the initialisation and the limb recovery score their
        hypotheses (each call draws afresh from it). Another seed is another equally good draw: tracking a
        capture with a few seeds shows how much of a difference between two settings the draw alone makes
        (`pipeline.lab.bench.retrack --seeds`).
    body : str
        The body model: the name of a body shipped with the tracker ("default", "paper"), or the path of
        a body file in their YAML layout (segments, DOFs and limits, ellipsoids, joints, length groups).
    """

    height_m: float | None = None
    stated_height_weight: float = 0.5
    distance: str = "normals"
    max_iterations: int = 10
    tolerance: float = 0.01
    displacement_m: float = 0.002
    estimate_lengths: tuple[str, ...] = ("upperarm", "shank", "girth", "forearm", "shoulders")
    sigma_m: float = 0.02
    min_observations: int = 30
    max_outlier_fraction: float = 0.6
    failure_sigma_m: float = 0.05
    reinit_every: int = 0
    reinit_margin: float = 0.05
    refit_drop: float = 0.1
    refit_iterations: int = 20
    restart_drop: float = 0.3
    velocity_decay: float = 0.7
    max_predicted_frames: int = 10
    scale_frames: int = 20
    init_headings: int = 12
    init_refine: int = 12
    normal_noise_deg: float = 10.0
    min_outlier_prior: float = 0.05
    max_sigma_m: float = 0.06
    limb_share_ratio: float = LIMB_SHARE_RATIO
    limb_min_observations: int = LIMB_MIN_OBSERVATIONS
    limb_check_every: int = 48
    seed: int = 0
    body: str = "default"

    def __post_init__(self) -> None:
        """Refuse, before any work, a value the tracker would fail on or silently misuse.

        Every field is checked for its type (an integer count, a finite number), its range and its
        relations to the others: a negative iteration count or prediction error ran and exported poses
        up to a metre off, a NaN width or zero headings ended in a traceback, an unknown distance
        stopped the run in its middle.
        """
        if self.height_m is not None:
            check_number("tracking.height_m", self.height_m, *SUBJECT_HEIGHT_RANGE_M, above=True)
        check_choice("tracking.distance", self.distance, tuple(DISTANCES))
        for name, minimum in _INTEGER_MINIMA.items():
            check_int(f"tracking.{name}", getattr(self, name), minimum)
        for name, (minimum, maximum, above) in _NUMBER_RANGES.items():
            check_number(f"tracking.{name}", getattr(self, name), minimum, maximum, above=above,
                         infinite=name in _MAY_BE_INFINITE)
        if not isinstance(self.body, str) or not self.body:
            raise InputError(f"tracking.body: expected the name of a shipped body or the path of a body file, "
                             f"got {self.body!r}")
        if not is_body_path(self.body):  # a body file is checked where the pipeline reads it (pipeline.io.body_io)
            check_length_groups(self.estimate_lengths, shipped_body(self.body))
        if not self.failure_sigma_m < self.max_sigma_m:
            raise InputError(f"tracking.failure_sigma_m: expected a value below max_sigma_m ({self.max_sigma_m}), "
                             f"since Σ never grows past that ceiling, got {self.failure_sigma_m}")

    def input_files(self) -> dict[str, Path]:
        """Files outside the capture and the code that tracking reads, by the parameter naming them: a body
        file given by its path (a shipped body is part of the code). Their contents belong in the stage's
        cache key, so that editing the file in place tracks again."""
        return {"body": Path(self.body)} if is_body_path(self.body) else {}

    @functools.cached_property
    def em(self) -> EMParams:
        """The EM's parameters of a tracked frame (the stopping rule, the distance and the noise model)."""
        return EMParams(distance=self.distance, max_iterations=self.max_iterations, tolerance=self.tolerance,
                        displacement_m=self.displacement_m, normal_noise_rad=np.radians(self.normal_noise_deg),
                        min_outlier_prior=self.min_outlier_prior, max_sigma_m=self.max_sigma_m)

    @functools.cached_property
    def init(self) -> InitParams:
        """The initialisation's parameters (the others at `InitParams`' defaults)."""
        return InitParams(headings=self.init_headings, refine=self.init_refine)

    @functools.cached_property
    def limbs(self) -> LimbParams:
        """When a limb is taken for misplaced and re-initialised."""
        return LimbParams(share_ratio=self.limb_share_ratio, min_observations=self.limb_min_observations)


# Smallest valid value of each integer field of TrackerParams.
_INTEGER_MINIMA = {"max_iterations": 1, "min_observations": 1, "reinit_every": 0, "refit_iterations": 1,
                   "max_predicted_frames": 0, "scale_frames": 0, "init_headings": 1, "init_refine": 1,
                   "limb_min_observations": 0, "limb_check_every": 0, "seed": 0}
# (minimum, maximum, strictly above the minimum) of each float field of TrackerParams. Σ starts from
# sigma_m² I, so a zero sigma_m is a singular covariance; a fraction or a prior are at most 1 (the
# outlier prior at most one half: the outlier class may not own most of the data).
_NUMBER_RANGES = {"tolerance": (0.0, np.inf, False), "displacement_m": (0.0, np.inf, False),
                  "sigma_m": (0.0, np.inf, True), "max_outlier_fraction": (0.0, 1.0, True),
                  "failure_sigma_m": (0.0, np.inf, True), "reinit_margin": (0.0, np.inf, False),
                  "refit_drop": (0.0, np.inf, False), "restart_drop": (0.0, np.inf, False),
                  "velocity_decay": (0.0, 1.0, False), "normal_noise_deg": (0.0, 90.0, False),
                  "min_outlier_prior": (0.0, 0.5, False), "max_sigma_m": (0.0, np.inf, True),
                  "limb_share_ratio": (0.0, 1.0, False), "stated_height_weight": (0.0, 1.0, False)}
# Thresholds that inf turns off (never refit, never restart).
_MAY_BE_INFINITE = ("refit_drop", "restart_drop")


def shipped_body(name: str) -> BodyModel:
    """The shipped body `name` (`body_file.load_body`), or a one-line error under `tracking.body`."""
    try:
        return load_body(name)
    except InputError as error:
        raise InputError(f"tracking.body: {error}") from None


def check_length_groups(names, body: BodyModel) -> None:
    """`estimate_lengths`: a tuple of distinct names of `body`'s length groups, else a one-line error."""
    known = sorted(body.length_groups)
    if not (isinstance(names, tuple) and all(isinstance(name, str) and name in known for name in names)
            and len(set(names)) == len(names)):
        raise InputError(f"tracking.estimate_lengths: expected a list of distinct length groups among "
                         f"{', '.join(known) or '(none)'} (those of body {body.name!r}), "
                         f"got {list(names) if isinstance(names, tuple) else names!r}")
