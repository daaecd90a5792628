"""The joint vocabulary of joints.csv (CAPTURE_FORMAT.md), shared by every stage.

The order is fixed so that arrays of joint positions can be indexed by position;
the first 15 joints are the ones scored by evaluation, the toes are optional.
"""

JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "neck", "head",
    "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist",
    "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle",
    "l_toe", "r_toe",
)
SCORED_JOINTS: tuple[str, ...] = JOINT_NAMES[:15]

#: A subject's standing height (metres) is above the first and at most the second: a toddler to the
#: tallest adults on record; outside it the value is a unit mistake (centimetres, millimetres).
SUBJECT_HEIGHT_RANGE_M: tuple[float, float] = (0.5, 2.6)
