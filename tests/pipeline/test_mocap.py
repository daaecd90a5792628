"""The mocap reader: forward kinematics, world frame, joint mapping, resampling, and its input checks."""

from pathlib import Path

import numpy as np
import pytest

from calib.errors import InputError
from pipeline.lab.mocap import load_clip
from stages.joints import JOINT_NAMES

DATA = Path(__file__).resolve().parents[2] / "pipeline" / "lab" / "data"
CLIPS = DATA / "clips"
J = {name: k for k, name in enumerate(JOINT_NAMES)}


@pytest.fixture(scope="module")
def kicks():
    return load_clip(CLIPS / "135_07.amc", skeleton=CLIPS / "martialwalk.asf")


@pytest.fixture(scope="module")
def leaning():
    return load_clip(CLIPS / "131_05.amc", skeleton=CLIPS / "mjackson.asf")


def test_clip_shapes_and_rate(kicks):
    assert kicks.fps == 120.0
    assert kicks.n_frames == 1472
    assert len(kicks.bone_names) == 31 and kicks.bone_names[0] == "root"
    assert kicks.joints.shape == (1472, 17, 3)
    assert np.all(kicks.parents[1:] < np.arange(1, 31))  # parents come first


def test_rest_pose_rotations_are_identity_and_bone_lengths_constant(kicks):
    lengths = np.linalg.norm(kicks.bone_ends - kicks.bone_origins, axis=2)  # (F, B)
    rest_lengths = np.linalg.norm(kicks.rest_ends - kicks.rest_origins, axis=1)
    np.testing.assert_allclose(lengths, np.broadcast_to(rest_lengths, lengths.shape), atol=1e-9)
    shin = np.linalg.norm(kicks.joints[:, J["l_knee"]] - kicks.joints[:, J["l_ankle"]], axis=1)
    assert np.ptp(shin) < 1e-9
    # femur: 7.12796 ASF units of (1 / 0.45) inch
    assert rest_lengths[kicks.bone_index("lfemur")] == pytest.approx(7.12796 * 0.0254 / 0.45, rel=1e-9)


def test_feet_on_the_floor(kicks, leaning):
    for motion in (kicks, leaning):
        feet = motion.joints[:, [J["l_toe"], J["r_toe"], J["l_ankle"], J["r_ankle"]], 2]  # (F, 4)
        lowest = feet.min(axis=1)
        assert 0.0 <= lowest.min() < 0.03  # the toe tips define the floor; the ball of the foot is just above
        # a standing or walking person has a foot on the floor nearly all the time
        assert np.mean(lowest < 0.08) > 0.85
        toe_tips = motion.bone_ends[:, [motion.bone_index("ltoes"), motion.bone_index("rtoes")], 2]
        assert toe_tips.min() == pytest.approx(0.0, abs=1e-12)


def test_standing_height_and_left_is_anatomical_left(kicks):
    assert 1.5 < kicks.joints[:, J["head"], 2].max() < 1.75  # a 1.7-1.8 m adult
    first = kicks.joints[0]
    forward = (first[J["l_toe"]] + first[J["r_toe"]] - first[J["l_ankle"]] - first[J["r_ankle"]]) * [1, 1, 0]
    left = np.cross([0.0, 0.0, 1.0], forward)
    assert np.dot(first[J["l_hip"]] - first[J["r_hip"]], left) > 0
    assert np.dot(first[J["l_shoulder"]] - first[J["r_shoulder"]], left) > 0


def test_joint_mapping_follows_the_documented_bones(kicks):
    frame = 100
    origins, ends = kicks.bone_origins[frame], kicks.bone_ends[frame]
    b = kicks.bone_index
    np.testing.assert_allclose(
        kicks.joints[frame, J["pelvis"]], (origins[b("lfemur")] + origins[b("rfemur")]) / 2
    )
    np.testing.assert_allclose(kicks.joints[frame, J["head"]], (origins[b("head")] + ends[b("head")]) / 2)
    np.testing.assert_allclose(kicks.joints[frame, J["neck"]], ends[b("thorax")], atol=1e-12)
    np.testing.assert_allclose(kicks.joints[frame, J["r_wrist"]], ends[b("rradius")], atol=1e-12)
    np.testing.assert_allclose(kicks.joints[frame, J["l_toe"]], ends[b("lfoot")], atol=1e-12)


@pytest.mark.parametrize(("amc", "asf"), [("135_07.amc", "martialwalk.asf"), ("131_05.amc", "mjackson.asf")])
def test_bvh_conversion_agrees_with_amc(amc, asf):
    from_amc = load_clip(CLIPS / amc, skeleton=CLIPS / asf)
    from_bvh = load_clip(DATA / "bvh" / amc.replace(".amc", ".bvh"))
    assert from_bvh.n_frames == from_amc.n_frames
    assert from_bvh.fps == pytest.approx(120.0, rel=1e-5)
    assert np.abs(from_bvh.joints - from_amc.joints).max() < 1e-3


def test_readme_facts_kicks(kicks):
    """135_07: toes reach 1.52-1.55 m in the kicks, the left kick at 3.68 s, the right at 0.99 s."""
    toe_tips = {side: kicks.bone_ends[:, kicks.bone_index(f"{side}toes"), 2] for side in "lr"}
    assert 1.52 <= toe_tips["l"].max() <= 1.56
    assert toe_tips["l"].argmax() / kicks.fps == pytest.approx(3.68, abs=0.1)
    first_right_kick = toe_tips["r"][: int(2.0 * kicks.fps)]
    assert first_right_kick.argmax() / kicks.fps == pytest.approx(0.99, abs=0.15)
    assert first_right_kick.max() > 1.3


def test_readme_facts_leaning(leaning):
    """131_05: the head joint goes down to about 0.85 m in the deep bend (between 5.5 and 8.5 s)."""
    head = leaning.joints[:, J["head"], 2]
    assert 0.8 < head.min() < 0.9
    assert 6.0 < head.argmin() / leaning.fps < 7.5
    assert head[: int(5 * leaning.fps)].min() > 1.35  # walking upright before the bend


def test_daz_bvh_maps_by_its_own_names():
    run = load_clip(CLIPS / "09_01.bvh")
    assert run.fps == pytest.approx(120.0, rel=1e-4)
    assert 1.4 < run.joints[10, J["head"], 2] < 1.8  # centimetres were recognised
    thigh = np.linalg.norm(run.joints[:, J["l_hip"]] - run.joints[:, J["l_knee"]], axis=1)
    assert np.ptp(thigh) < 1e-9
    speed = np.linalg.norm(run.joints[-1, J["pelvis"], :2] - run.joints[1, J["pelvis"], :2]) / (
        (run.n_frames - 2) / run.fps
    )
    assert 2.8 < speed < 4.0  # a fast run, about 3.4 m/s


def test_resample_to_half_rate_hits_original_frames(kicks):
    half = kicks.resample(60.0)
    assert half.fps == 60.0 and half.n_frames == 736
    np.testing.assert_allclose(half.joints, kicks.joints[::2], atol=1e-9)


def test_resample_to_28fps_keeps_lengths_and_interpolates(kicks):
    slow = kicks.resample(28.0)
    assert slow.n_frames == int(np.floor(kicks.duration * 28)) + 1
    lengths = np.linalg.norm(slow.bone_ends - slow.bone_origins, axis=2)
    np.testing.assert_allclose(lengths, lengths[:1].repeat(len(lengths), 0), atol=1e-9)
    # frame 7 at 0.25 s lies on the original frame 30 exactly
    np.testing.assert_allclose(slow.joints[7], kicks.joints[30], atol=1e-9)
    # in between, joints move at most a little from the neighbouring originals (no wild interpolation)
    t = 5 / 28 * 120  # original frame 21.43
    gap = np.linalg.norm(slow.joints[5] - kicks.joints[int(t)], axis=1).max()
    assert gap < np.linalg.norm(kicks.joints[int(t) + 1] - kicks.joints[int(t)], axis=1).max() + 1e-3


def test_slice_seconds_keeps_the_world_frame(kicks):
    part = kicks.slice_seconds(1.0, 2.0)
    assert part.n_frames == 120
    np.testing.assert_array_equal(part.joints, kicks.joints[120:240])
    with pytest.raises(InputError, match="holds no frame"):
        kicks.slice_seconds(20.0, 21.0)


# ------------------------------------------------------------------------------------------ input checks


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_amc_without_skeleton_is_an_input_error():
    with pytest.raises(InputError, match="needs its ASF skeleton"):
        load_clip(CLIPS / "135_07.amc")


def test_unknown_suffix_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="unknown clip type"):
        load_clip(_write(tmp_path, "clip.c3d", "x"))


def test_asf_bone_without_axis_names_file_and_line(tmp_path):
    text = (CLIPS / "martialwalk.asf").read_text().replace("     axis 0 0 20  XYZ\n", "", 1)
    asf = _write(tmp_path, "broken.asf", text)
    with pytest.raises(InputError, match=r"broken\.asf:\d+: bone block has no 'axis'"):
        load_clip(CLIPS / "135_07.amc", skeleton=asf)


def test_amc_wrong_value_count_names_file_and_line(tmp_path):
    lines = (CLIPS / "135_07.amc").read_text().splitlines()[:60]
    lines[10] = "rradius 1 2"
    amc = _write(tmp_path, "broken.amc", "\n".join(lines))
    with pytest.raises(InputError, match=r"broken\.amc:11: bone 'rradius' has 2 values; expected 1"):
        load_clip(amc, skeleton=CLIPS / "martialwalk.asf")


def test_amc_unknown_bone_is_an_input_error(tmp_path):
    lines = (CLIPS / "135_07.amc").read_text().splitlines()[:60]
    lines[6] = "tail 1 2 3"
    amc = _write(tmp_path, "tail.amc", "\n".join(lines))
    with pytest.raises(InputError, match=r"tail\.amc:7: unknown bone 'tail'"):
        load_clip(amc, skeleton=CLIPS / "martialwalk.asf")


BVH_HEADER = """HIERARCHY
ROOT {root}
{{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT {child}
  {{
    OFFSET 0 -90 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {{
      OFFSET 0 -10 0
    }}
  }}
}}
MOTION
Frames: 1
Frame Time: 0.04
0 100 0 0 0 0 0 0 0
"""


def test_bvh_unknown_joint_names_is_an_input_error(tmp_path):
    bvh = _write(tmp_path, "robot.bvh", BVH_HEADER.format(root="base", child="arm"))
    with pytest.raises(InputError, match=r"robot\.bvh: unknown joint names"):
        load_clip(bvh)


def test_bvh_wrong_value_count_names_line(tmp_path):
    bvh = _write(
        tmp_path, "short.bvh", BVH_HEADER.format(root="hip", child="lThigh").replace("0 100 0 0", "0 100")
    )
    with pytest.raises(InputError, match=r"short\.bvh:19: 7 values; expected 9"):
        load_clip(bvh)


def test_bvh_truncated_hierarchy_is_an_input_error(tmp_path):
    text = (DATA / "bvh" / "131_05.bvh").read_text().splitlines()
    bvh = _write(tmp_path, "cut.bvh", "\n".join(text[:40] + ["MOTION", "Frames: 1", "Frame Time: 0.01"]))
    with pytest.raises(InputError, match=r"cut\.bvh: file ends inside the HIERARCHY"):
        load_clip(bvh)


def test_bvh_bad_channel_names_line(tmp_path):
    bvh = _write(
        tmp_path,
        "chan.bvh",
        BVH_HEADER.format(root="hip", child="lThigh").replace("Xrotation Y", "Wrotation Y", 1),
    )
    with pytest.raises(InputError, match=r"chan\.bvh:5: unknown channel 'Wrotation'"):
        load_clip(bvh)


def test_held_prepends_the_first_pose_still(kicks):
    span = kicks.slice_seconds(1.0, 1.5)
    held = span.held(0.25)
    still = round(0.25 * span.fps)
    assert held.n_frames == span.n_frames + still
    assert np.array_equal(held.joints[:still + 1], np.broadcast_to(span.joints[0], (still + 1, *span.joints.shape[1:])))
    assert np.array_equal(held.joints[still:], span.joints)
    with pytest.raises(InputError, match="hold"):
        span.held(-1.0)
