"""The articulated ellipsoid body: kinematic tree, forward kinematics and its derivatives.

A body is a tree of rigid segments joined by revolute degrees of freedom (DOF); each segment carries
ellipsoids (Horaud et al. 2009, Sec. 2.2) and some of the 17 joint centres of `stages.joints`. The
geometry lives in YAML files (`bodies/<name>.yaml`, read by `body_file`) as fractions of standing height,
so a user edits a body without touching code and one number scales it.

Pose vector Λ (D,): the root's translation (3, metres, world), the root's rotation as yaw about world
z, pitch and roll (3, radians), then every joint DOF in segment order (radians). Pose zero is the
body standing upright at the origin facing +y, x to its right.

Derivatives follow from the chain structure: a revolute DOF with world axis w through the point o
moves every point x of the segments below it by dx/dθ = w × (x − o) and turns their rotations by
dR/dθ = [w]× R; a translational DOF moves them by dx/dθ = w.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, replace

import numpy as np

from calib.errors import InputError
from stages.tracking import compiled


@dataclass(frozen=True)
class Ellipsoids:
    """Posed ellipsoids: x is on ellipsoid p when (x − t_p)ᵀ R_p D_p R_pᵀ (x − t_p) = 1.

    Attributes
    ----------
    R : (E, 3, 3) float
        World rotation R_p; its columns are the directions of the semi-axes.
    t : (E, 3) float
        World centre t_p, metres.
    semi_axes : (E, 3) float
        Semi-axes (a, b, c), metres; D_p = diag(a⁻², b⁻², c⁻²).
    """

    R: np.ndarray
    t: np.ndarray
    semi_axes: np.ndarray

    @functools.cached_property
    def shapes(self) -> tuple[np.ndarray, np.ndarray]:
        """M_p = R_p diag(a²) R_pᵀ and M_p² (E, 3, 3) each (`compiled.shapes`), the shape matrices of eq. (4).

        An EM iteration reads them in the M-step's normal equations, its covariance and the next E-step, all
        at the same pose: computed once per posed body.
        """
        return compiled.shapes(self.R, self.semi_axes)


@dataclass(frozen=True)
class Kinematics:
    """Forward kinematics of one pose.

    Attributes
    ----------
    R : (S, 3, 3) float
        World rotation of every segment frame (identity in the zero pose).
    t : (S, 3) float
        World position of every segment's joint centre, metres.
    axis : (D, 3) float
        World direction of every DOF (unit; for translations the direction moved along).
    origin : (D, 3) float
        A world point on every revolute DOF's axis (its joint centre), metres.
    ellipsoids : Ellipsoids
        The body's ellipsoids placed on these frames (`BodyModel.ellipsoids`). They are posed with the
        frames because every pose EM visits needs them, several times per iteration.
    """

    R: np.ndarray
    t: np.ndarray
    axis: np.ndarray
    origin: np.ndarray
    ellipsoids: Ellipsoids


@dataclass(frozen=True)
class BodyModel:
    """An articulated body of ellipsoids, in metres (see the module docstring for the pose vector).

    Attributes
    ----------
    name : str
        The body file's `name` (a shipped body's is its file stem; a body given by its path keeps its own).
    height_m : float
        Standing height the lengths are scaled to, metres.
    segment_names : tuple of str
        Segments in topological order (every parent before its children); segment 0 is the root.
    parent : (S,) int
        Parent segment index, −1 for the root.
    offset : (S, 3) float
        Joint centre of each segment in its parent's frame (root: 0), metres.
    dof_names : tuple of str
        "<segment>.<dof>" for every entry of the pose vector.
    dof_segment : (D,) int
        Segment whose joint each DOF belongs to.
    dof_axis : (D, 3) float
        Unit axis of each DOF in its joint frame.
    dof_revolute : (D,) bool
        True for rotations (radians), False for the root translations (metres).
    lower, upper : (D,) float
        Joint limits (±inf where free).
    prior_weight : (D,) float
        Weight of a soft pull towards the predicted value, for DOFs the data barely constrain (twist).
    moves : (D, S) bool
        moves[d, s]: DOF d moves segment s (s is d's segment or one of its descendants).
    ellipsoid_segment : (E,) int
        Segment carrying each ellipsoid.
    ellipsoid_rotation : (E, 3, 3) float
        Ellipsoid axes in its segment's frame.
    ellipsoid_centre : (E, 3) float
        Ellipsoid centre in its segment's frame, metres (relative to the segment's joint centre).
    semi_axes : (E, 3) float
        Semi-axes (a, b, c), metres.
    standing_root : (3,) float
        World position of the root's joint centre when standing on the floor at the origin, metres.
    joint_segment : (17,) int
        Segment carrying each joint of `JOINT_NAMES`.
    joint_offset : (17, 3) float
        Joint centre in its segment's frame, metres.
    length_groups : tuple of str
        Names of the segment-length factors (e.g. "thigh" for both thighs), possibly empty.
    length_group : (S,) int
        Length factor stretching each segment, −1 for segments of fixed length.
    length_axis : (S, 3) float
        Unit direction, in the segment's frame, along which its length factor stretches it.
    length_factors : (G,) float
        Current length factors (1 = the configuration's proportions).
    length_prior_sd : (G,) float
        Standard deviation of the prior on each ln ℓ towards 0 (the file's proportions): how much
        that factor varies between adults.
    girth_group : (E,) int
        Girth factor (a group of `length_groups` whose axis is "girth") scaling each ellipsoid's two
        short semi-axes, −1 for ellipsoids of fixed girth.
    joint_group : (S,) int
        Factor (a group of `length_groups` with `scales: joint`) scaling where each segment's joint sits
        in its parent (its `offset`) along `joint_axis`, −1 for segments whose joint stays: the shoulder
        width, which moves the arms without widening the chest's ellipsoids.
    joint_axis : (S, 3) float
        Unit direction, in the parent's frame, along which that factor moves the segment's joint.
    """

    name: str
    height_m: float
    segment_names: tuple[str, ...]
    parent: np.ndarray
    offset: np.ndarray
    dof_names: tuple[str, ...]
    dof_segment: np.ndarray
    dof_axis: np.ndarray
    dof_revolute: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    prior_weight: np.ndarray
    moves: np.ndarray
    ellipsoid_segment: np.ndarray
    ellipsoid_rotation: np.ndarray
    ellipsoid_centre: np.ndarray
    semi_axes: np.ndarray
    standing_root: np.ndarray
    joint_segment: np.ndarray
    joint_offset: np.ndarray
    length_groups: tuple[str, ...]
    length_group: np.ndarray
    length_axis: np.ndarray
    length_factors: np.ndarray
    length_prior_sd: np.ndarray
    girth_group: np.ndarray
    joint_group: np.ndarray
    joint_axis: np.ndarray

    @property
    def pose_size(self) -> int:
        """Number of pose parameters D."""
        return len(self.dof_names)

    @property
    def n_ellipsoids(self) -> int:
        return len(self.ellipsoid_segment)

    def zero_pose(self) -> np.ndarray:
        """The pose standing upright on the floor at the origin, facing +y, (D,)."""
        pose = np.zeros(self.pose_size)
        pose[:3] = self.standing_root
        return pose

    def clip(self, pose: np.ndarray) -> np.ndarray:
        """The pose with every DOF inside its joint limits."""
        return np.clip(pose, self.lower, self.upper)

    def fk(self, pose: np.ndarray) -> Kinematics:
        """Forward kinematics: segment frames, world DOF axes and posed ellipsoids of `pose` (D,)."""
        return _forward_kinematics(self, np.asarray(pose, dtype=float))

    def ellipsoids(self, pose_or_kin: np.ndarray | Kinematics) -> Ellipsoids:
        """World ellipsoids (R_p, t_p, semi-axes) of a pose (D,) or of its kinematics (this body's `fk`)."""
        return self._kinematics(pose_or_kin).ellipsoids

    def posed_ellipsoids(self, poses: np.ndarray) -> Ellipsoids:
        """`ellipsoids` of many poses (H, D) at once, as arrays with a leading pose axis (H, E, ...)."""
        poses = np.asarray(poses, dtype=float)
        if poses.ndim != 2 or poses.shape[1] != self.pose_size:
            raise ValueError(f"poses have shape {poses.shape}, expected (H, {self.pose_size})")
        R, t = compiled.posed_ellipsoids(self.parent, self.offset, self._dof_start, self.dof_axis,
                                         self.dof_revolute, poses, self.ellipsoid_segment,
                                         self.ellipsoid_rotation, self.ellipsoid_centre)
        return Ellipsoids(R=R, t=t, semi_axes=np.broadcast_to(self.semi_axes, (len(poses),) + self.semi_axes.shape))

    def joint_positions(self, pose_or_kin: np.ndarray | Kinematics) -> np.ndarray:
        """World joint centres (17, 3) in `JOINT_NAMES` order, metres."""
        kin = self._kinematics(pose_or_kin)
        R_seg = kin.R[self.joint_segment]
        return kin.t[self.joint_segment] + np.einsum("jab,jb->ja", R_seg, self.joint_offset)

    def segment_twists(self, kin: Kinematics) -> np.ndarray:
        """Rigid velocity of every segment per unit change of every DOF, T (S, 6, D).

        A segment moving with angular velocity ω and linear velocity v (of the world origin) moves its
        point x by ω × x + v; column d of T[s] is (ω, v) = (w_d, o_d × w_d) for a revolute DOF with
        world axis w_d through o_d, (0, w_d) for a translation along w_d, and zero when d does not
        move s.
        """
        T = np.zeros((len(self.segment_names), 6, self.pose_size))
        w = kin.axis.T  # (3,D)
        o = kin.origin.T
        moment = np.stack([o[1] * w[2] - o[2] * w[1], o[2] * w[0] - o[0] * w[2], o[0] * w[1] - o[1] * w[0]])  # o × w
        v = np.where(self.dof_revolute[None, :], moment, w)
        T[:, :3, :] = np.where(self.dof_revolute[None, :], w, 0.0)[None]
        T[:, 3:, :] = v[None]
        return T * self.moves.T[:, None, :]

    def point_jacobian(self, kin: Kinematics, x: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """Derivatives (N, 3, D) of body-fixed world points x (N, 3) riding on `segment` (N,).

        dx/dθ_d = ω_d × x + v_d with (ω_d, v_d) the segment's rigid velocity (`segment_twists`).
        """
        B = np.concatenate([-skew(x), np.broadcast_to(np.eye(3), x.shape + (3,))], axis=2)  # (N,3,6)
        return B @ self.segment_twists(kin)[segment]

    def joint_jacobian(self, pose_or_kin: np.ndarray | Kinematics) -> np.ndarray:
        """Derivatives (17, 3, D) of `joint_positions` with respect to the pose."""
        kin = self._kinematics(pose_or_kin)
        return self.point_jacobian(kin, self.joint_positions(kin), self.joint_segment)

    def scaled(self, height_m: float) -> BodyModel:
        """The same body scaled to another standing height (metres)."""
        if not np.isfinite(height_m) or height_m <= 0:
            raise InputError(f"height_m: got {height_m!r}, expected a positive number of metres")
        s = height_m / self.height_m
        return replace(self, height_m=float(height_m), offset=self.offset * s,
                       ellipsoid_centre=self.ellipsoid_centre * s, semi_axes=self.semi_axes * s,
                       standing_root=self.standing_root * s, joint_offset=self.joint_offset * s)

    def with_lengths(self, factors: np.ndarray) -> BodyModel:
        """The same body with segment-length factors `factors` (G,) (absolute, 1 = as configured).

        Segment s of a length group is stretched by S = I + (ℓ − 1) u uᵀ along its axis u (in its
        frame): the offsets of its child joints, the joint centres and ellipsoid centres it carries,
        and the shapes of its ellipsoids (an ellipsoid (x − t)ᵀ A⁻¹ (x − t) = 1 with A = R diag(a²) Rᵀ
        maps to A' = S A Sᵀ). A girth group instead scales the two short semi-axes of its ellipsoids,
        joints untouched: bodies differ in build as well as in height, and without it the overall size
        (`scaled`) is the only way to fit a stouter body, which makes it too tall. A joint group moves
        its segments' joints in their parents (the offsets, along `joint_axis`), carrying the segments
        along unchanged: the shoulder width, without widening the chest. Stretches along one axis
        compose, so the change from the current factors is the stretch by their ratio.
        """
        factors = np.asarray(factors, dtype=float)
        if factors.shape != self.length_factors.shape or not np.all(factors > 0):
            raise ValueError(f"length factors: expected {len(self.length_groups)} positive numbers, "
                             f"got {factors.tolist()}")
        if np.array_equal(factors, self.length_factors):
            return self
        return self.with_each_lengths(factors[None])[0]

    def length_derivatives(self, kin: Kinematics) -> tuple[np.ndarray, np.ndarray]:
        """How the posed ellipsoids of `kin` move as each length factor grows: dt_p / d ln ℓ_g (G, E, 3) and
        dM_p / d ln ℓ_g (G, E, 3, 3), M_p = R_p diag(a²) R_pᵀ (world frame), at the current factors.

        These are the derivatives of `with_lengths` at ℓ: a stretch S = I + (ℓ − 1) u uᵀ changes by u uᵀ per unit
        ln ℓ, so a stretched segment's ellipsoid centres c move by u (u · c) and its shapes by
        ũ (M ũ)ᵀ + (M ũ) ũᵀ (ũ = R_s u in the world), and each joint it carries by u (u · offset), taking the
        child segment and everything below it along; a joint group moves its joints by a (a · offset) along its
        axis a; a girth grows the two short semi-axes, dM = 2 (M − a₀² r₀ r₀ᵀ), r₀ the long axis. Exact, and
        without the eigen-decompositions that differencing `with_each_lengths` would cost per factor.
        """
        G, S = len(self.length_groups), len(self.segment_names)
        ellipsoids, segment = kin.ellipsoids, self.ellipsoid_segment
        M = ellipsoids.shapes[0]
        # Each segment's joint moved in its parent's frame, per factor (G, S, 3), then in the world.
        moved = np.zeros((G, S, 3))
        child = np.flatnonzero(self.parent >= 0)
        stretched = child[self.length_group[self.parent[child]] >= 0]  # joints carried by a stretched parent
        u = self.length_axis[self.parent[stretched]]
        moved[self.length_group[self.parent[stretched]], stretched] += u * np.einsum("sa,sa->s", u,
                                                                                     self.offset[stretched])[:, None]
        shifted = np.flatnonzero(self.joint_group >= 0)
        a = self.joint_axis[shifted]
        moved[self.joint_group[shifted], shifted] += a * np.einsum("sa,sa->s", a, self.offset[shifted])[:, None]
        moved[:, child] = np.einsum("sab,gsb->gsa", kin.R[self.parent[child]], moved[:, child])
        frame = np.einsum("as,gaj->gsj", self._lineage, moved)  # every segment moves with the joints above it
        dt = frame[:, segment]  # (G, E, 3)
        dM = np.zeros((G, self.n_ellipsoids, 3, 3))
        on = np.flatnonzero(self.length_group[segment] >= 0)  # ellipsoids of stretched segments
        g, s = self.length_group[segment[on]], segment[on]
        u_world = np.einsum("kab,kb->ka", kin.R[s], self.length_axis[s])
        dt[g, on] += u_world * np.einsum("ka,ka->k", self.length_axis[s], self.ellipsoid_centre[on])[:, None]
        Mu = np.einsum("kab,kb->ka", M[on], u_world)
        dM[g, on] += u_world[:, :, None] * Mu[:, None, :] + Mu[:, :, None] * u_world[:, None, :]
        thick = np.flatnonzero(self.girth_group >= 0)
        r0 = ellipsoids.R[thick, :, 0]
        dM[self.girth_group[thick], thick] += 2.0 * (
            M[thick] - (ellipsoids.semi_axes[thick, 0] ** 2)[:, None, None] * r0[:, :, None] * r0[:, None, :])
        return dt, dM

    @functools.cached_property
    def _lineage(self) -> np.ndarray:
        """`lineage` of this body's segments, computed once per body."""
        return lineage(self.parent)

    def with_each_lengths(self, factors: np.ndarray) -> tuple[BodyModel, ...]:
        """`with_lengths` of every row of `factors` (B, G), computed together.

        A distance without closed-form length derivatives differences its residuals by each factor in turn
        (`distances.Distance.length_jacobian`): one body per factor, and stretching them at once costs little
        more than one, most of `with_lengths`'s cost being per call rather than per segment.
        """
        factors = np.asarray(factors, dtype=float)
        if factors.ndim != 2 or factors.shape[1] != len(self.length_groups) or not np.all(factors > 0):
            raise ValueError(f"length factors: expected rows of {len(self.length_groups)} positive numbers, "
                             f"got {factors.tolist()}")
        group_ratio = factors / self.length_factors  # (B,G)
        ratio = np.ones((len(factors), len(self.segment_names)))
        grouped = self.length_group >= 0
        ratio[:, grouped] = group_ratio[:, self.length_group[grouped]]
        u = self.length_axis
        S = np.eye(3) + (ratio - 1.0)[:, :, None, None] * u[:, :, None] * u[:, None, :]  # (B,S,3,3)
        offset = np.repeat(self.offset[None], len(factors), axis=0)
        offset[:, 1:] = np.einsum("zsab,sb->zsa", S[:, self.parent[1:]], self.offset[1:])
        moved = self.joint_group >= 0
        along = np.einsum("zsa,sa->zs", offset[:, moved], self.joint_axis[moved])
        offset[:, moved] += ((group_ratio[:, self.joint_group[moved]] - 1.0)[:, :, None] * along[:, :, None]
                             * self.joint_axis[moved])
        S_e = S[:, self.ellipsoid_segment]  # (B,E,3,3)
        rotation = np.repeat(self.ellipsoid_rotation[None], len(factors), axis=0)
        semi_axes = np.repeat(self.semi_axes[None], len(factors), axis=0)
        stretched = ratio[:, self.ellipsoid_segment] != 1.0  # the others keep their shape exactly
        if np.any(stretched):
            e = np.nonzero(stretched)[1]
            R, a, S_s = self.ellipsoid_rotation[e], self.semi_axes[e], S_e[stretched]
            A = np.einsum("eab,eb,ecb->eac", R, a**2, R)
            rotation[stretched], semi_axes[stretched] = _principal_axes(S_s @ A @ S_s.transpose(0, 2, 1), R)
        girth = self.girth_group >= 0
        semi_axes[:, girth, 1:] *= group_ratio[:, self.girth_group[girth], None]
        centre = np.einsum("zeab,eb->zea", S_e, self.ellipsoid_centre, order="C")  # compiled for C arrays
        joint_offset = np.einsum("zjab,jb->zja", S[:, self.joint_segment], self.joint_offset, order="C")
        return tuple(replace(self, offset=offset[b], ellipsoid_rotation=rotation[b], semi_axes=semi_axes[b],
                             ellipsoid_centre=centre[b], joint_offset=joint_offset[b],
                             length_factors=factors[b].copy()) for b in range(len(factors)))

    def with_length_groups(self, names: tuple[str, ...]) -> BodyModel:
        """The same body with only the length groups `names` left free (in that order).

        The segments of the other groups keep their current stretch, now fixed: the tracker estimates
        only the lengths the data pin down (`TrackerParams.estimate_lengths`), while a group whose
        estimate trades off against another one (a longer thigh for a shorter shank moves little but the
        knee) stays at the body file's proportions.

        Raises
        ------
        InputError
            If a name is not one of the body's length groups.
        """
        unknown = [name for name in names if name not in self.length_groups]
        if unknown:
            raise InputError(f"length groups {unknown}: body {self.name!r} has {list(self.length_groups)}")
        old = np.array([self.length_groups.index(name) for name in names], dtype=int)
        new_index = np.full(len(self.length_groups) + 1, -1)  # last entry: segments of no group stay -1
        new_index[old] = np.arange(len(old))
        return replace(self, length_groups=tuple(names), length_group=new_index[self.length_group],
                       girth_group=new_index[self.girth_group], joint_group=new_index[self.joint_group],
                       length_factors=self.length_factors[old].copy(),
                       length_prior_sd=self.length_prior_sd[old].copy())

    @functools.cached_property
    def _dof_start(self) -> np.ndarray:
        """(S + 1,) int: the DOFs of segment s are dof_start[s]:dof_start[s + 1] (they are in segment order)."""
        return np.searchsorted(self.dof_segment, np.arange(len(self.segment_names) + 1))

    def _kinematics(self, pose_or_kin: np.ndarray | Kinematics) -> Kinematics:
        return pose_or_kin if isinstance(pose_or_kin, Kinematics) else self.fk(pose_or_kin)


def lineage(parent: np.ndarray) -> np.ndarray:
    """(S, S) bool: lineage[a, s] when segment a is s or one of its ancestors, for segments in topological order
    with ``parent`` (S,) (−1 for the root): whatever moves segment a moves s."""
    ancestry = np.eye(len(parent), dtype=bool)
    for s, a in enumerate(parent):  # a parent's column is complete before its child's
        if a >= 0:
            ancestry[:, s] |= ancestry[:, a]
    return ancestry


def sample_surface(body: BodyModel, pose: np.ndarray, count: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points (count, 3) on the posed body's ellipsoids, about uniform in area, with their outward
    unit normals (count, 3): the data a perfect reconstruction of this very body would give, for the
    compile warm-up and the tracker's tests.
    """
    ell = body.ellipsoids(pose)
    a = ell.semi_axes
    area = a[:, 0] * a[:, 1] + a[:, 1] * a[:, 2] + a[:, 0] * a[:, 2]  # proportional to the area
    p = rng.choice(len(a), count, p=area / area.sum())
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = np.einsum("kab,kb->ka", ell.R[p], u * a[p]) + ell.t[p]
    n = np.einsum("kab,kb->ka", ell.R[p], u / a[p])
    return y, n / np.linalg.norm(n, axis=1, keepdims=True)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]× (..., 3, 3) of vectors v (..., 3)."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def _principal_axes(A: np.ndarray, like: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axes (E, 3, 3) and semi-axes (E, 3) of ellipsoid matrices A = R diag(semi²) Rᵀ (E, 3, 3).

    The eigenvectors are ordered and signed like the columns of `like` (E, 3, 3), so that a stretch
    along an ellipsoid's own axis keeps its frame.
    """
    values, vectors = np.linalg.eigh(A)
    match = np.abs(np.einsum("eai,eaj->eij", like, vectors))  # |cos| between old axis i and new j
    fit = match[:, np.arange(3), _PERMUTATIONS].sum(axis=2)  # (E,6); a permutation even when b = c
    order = _PERMUTATIONS[np.argmax(fit, axis=1)]  # (E,3): new axis for old axis i
    R = np.take_along_axis(vectors, order[:, None, :], axis=2)
    R *= np.sign(np.einsum("eai,eai->ei", like, R))[:, None, :]
    x, y = R[:, :, 0], R[:, :, 1]  # keep it a rotation: third axis x × y, written out (np.cross costs ~50 µs)
    R[:, 0, 2], R[:, 1, 2], R[:, 2, 2] = (x[:, 1] * y[:, 2] - x[:, 2] * y[:, 1], x[:, 2] * y[:, 0] - x[:, 0] * y[:, 2],
                                          x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0])
    return R, np.sqrt(np.take_along_axis(values, order, axis=1))


# The orderings of three axes (6, 3), for `_principal_axes`.
_PERMUTATIONS = np.array(list(itertools.permutations(range(3))))


def _forward_kinematics(body: BodyModel, pose: np.ndarray) -> Kinematics:
    if pose.shape != (body.pose_size,):
        raise ValueError(f"pose has shape {pose.shape}, expected ({body.pose_size},)")
    R, t, axis, origin, R_e, t_e = compiled.posed_body(body.parent, body.offset, body._dof_start, body.dof_axis,
                                                       body.dof_revolute, pose, body.ellipsoid_segment,
                                                       body.ellipsoid_rotation, body.ellipsoid_centre)
    return Kinematics(R=R, t=t, axis=axis, origin=origin, ellipsoids=Ellipsoids(R=R_e, t=t_e, semi_axes=body.semi_axes))
