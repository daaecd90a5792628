"""Calibration suite: ``python -m pipeline calibrate`` on rendered board recordings, scored against the true rig.

Scenarios:

- ``checkerboard`` and ``charuco``: the bundled taekwondo rig (6 cameras 780x580, lens distortion, 3.3-5.4 m
  from the middle), a board of about 1 x 0.7 m rendered by :mod:`pipeline.lab.synth.boards` (studio room, noise,
  blur): views in front of each camera for its intrinsics, poses in the middle of the ring each seen by two or
  three cameras, and the board on the floor at three places (``--floor floor,floor1,floor2``; ``floor`` lies
  on the true world's origin and axes, so the calibrated world should be the true one). Scored per camera:
  focal length (%), principal point (px), camera centre (mm) and rotation (degrees), both as written (the
  floor frame against the true world) and after the rigid motion that best aligns the camera centres (what the
  rig's geometry owes to the floor's), and the tilt of the calibrated floor.
- ``phone``: one portrait 1088x1920 camera (a phone) and 7 views of a printed A4 checkerboard of 4 x 7 inner
  corners, intrinsics only; scored on its focal length.
- ``taekwondo``: the bundled capture run again with its calibration replaced by the checkerboard scenario's
  (same cameras, same media), against the run on its true calibration: MPJPE of each.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from calib.board import parse_board
from calib.camera import Camera, Rig
from calib.formats import load_rig
from pipeline.evaluate import evaluate_run
from pipeline.lab.bench.recipes import generator_version
from pipeline.lab.bench.runs import REPO, run_pipeline
from pipeline.lab.bench.tables import format_table
from pipeline.lab.synth.boards import write_board_recording

BOARDS = {"checkerboard": "checkerboard:8x5:0.11", "charuco": "charuco:7x5:0.14:0.084:DICT_4X4_50"}
#: The boards calibrated with their floor views: no camera of the taekwondo rig decodes the ChArUco markers of a
#: board lying on the floor 3-5 m away, so that scenario's world is the first camera's and it is scored aligned.
WITH_FLOOR = {"checkerboard": True, "charuco": False}
PHONE_BOARD = "checkerboard:4x7:0.025"
FLOOR = "floor,floor1,floor2"
TAEKWONDO = REPO / "data_samples" / "taekwondo"
#: Views rendered: (intrinsic per camera, extrinsic poses) for a full and a quick run.
VIEWS = {False: (15, 40), True: (6, 14)}
PHONE_VIEWS = 7
#: Frames of taekwondo processed by a quick run.
QUICK_FRAMES = 28


def _recording(captures: Path, name: str, recipe: dict, render) -> Path:
    """``captures/<name>``, rendered by ``render(path)`` unless its ``recipe.json`` already matches."""
    folder = captures / name
    stamp = captures / f"{name}.recipe.json"
    if folder.is_dir() and stamp.is_file() and json.loads(stamp.read_text()) == recipe:
        return folder
    if folder.exists():
        shutil.rmtree(folder)  # a bench cache entry: a stale or interrupted rendering
    stamp.unlink(missing_ok=True)
    captures.mkdir(parents=True, exist_ok=True)
    render(folder)
    stamp.write_text(json.dumps(recipe))
    return folder


def phone_camera() -> Camera:
    """A portrait phone camera: 1088 x 1920, 26 mm-equivalent lens (fx about 1500 px), mild barrel distortion."""
    K = np.array([[1512.0, 0.0, 547.3], [0.0, 1509.0, 955.8], [0.0, 0.0, 1.0]])
    return Camera("phone", K, np.array([0.06, -0.12, 0.0, 0.0, 0.0]), np.eye(3), np.zeros(3), (1088, 1920))


def _calibrate(boards: Path, board: str, out: Path, floor: str | None) -> dict:
    """Run the command; its wall time, exit status and last lines."""
    shutil.rmtree(out, ignore_errors=True)
    command = [sys.executable, "-m", "pipeline", "calibrate", str(boards), "--board", board, "--out", str(out), "-q"]
    if floor:
        command += ["--floor", floor]
    started = time.perf_counter()
    result = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    return {"returncode": result.returncode, "seconds": time.perf_counter() - started,
            "log_tail": "\n".join((result.stdout + result.stderr).strip().splitlines()[-6:])}


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(A @ B.T)[0])))


def _alignment(got: np.ndarray, want: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the rigid motion taking the points ``got`` (N, 3) closest to ``want`` (Kabsch, no scale)."""
    got_mean, want_mean = got.mean(axis=0), want.mean(axis=0)
    U, _, Vt = np.linalg.svd((want - want_mean).T @ (got - got_mean))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return R, want_mean - R @ got_mean


def score_rig(calibrated: Rig, truth: Rig) -> dict:
    """Worst camera's errors: focal %, principal point px, centre mm and rotation degrees (as written and aligned)."""
    R_align, t_align = _alignment(calibrated.centres, truth.centres)
    rows = []
    for got, want in zip(calibrated, truth, strict=True):
        aligned_centre = R_align @ got.centre + t_align
        rows.append({"camera": got.name,
                     "focal_percent": float(100 * np.max(np.abs(np.diag(got.K)[:2] / np.diag(want.K)[:2] - 1))),
                     "principal_px": float(np.linalg.norm(got.K[:2, 2] - want.K[:2, 2])),
                     "centre_mm": float(1000 * np.linalg.norm(got.centre - want.centre)),
                     "rotation_deg": _angle_deg(got.R, want.R),
                     "aligned_centre_mm": float(1000 * np.linalg.norm(aligned_centre - want.centre)),
                     "aligned_rotation_deg": _angle_deg(got.R @ R_align.T, want.R)})
    worst = {key: max(row[key] for row in rows) for key in rows[0] if key != "camera"}
    worst["floor_tilt_deg"] = float(np.degrees(np.arccos(np.clip(R_align[2, 2], -1, 1))))
    return {"cameras": rows, **worst}


def _board_scenario(name: str, captures: Path, out: Path, rig: Rig, quick: bool) -> dict:
    intrinsic, extrinsic = VIEWS[quick]
    board = BOARDS[name]
    recipe = {"board": board, "intrinsic": intrinsic, "extrinsic": extrinsic, "floor": 3, "seed": 17,
              "rig": "data_samples/taekwondo", "generator": generator_version()}
    boards = _recording(captures, f"calibration-{name}{'-quick' if quick else ''}", recipe, lambda path: (
        write_board_recording(rig, parse_board(board), path, intrinsic_views=intrinsic, extrinsic_views=extrinsic,
                              floor_views=3, seed=17)))
    capture = out / "calibration" / name
    row = {"scenario": name, "board": board, "cameras": len(rig), "size": "780x580",
           "views": f"{intrinsic} per camera + {extrinsic} shared + 3 floor",
           **_calibrate(boards, board, capture, FLOOR if WITH_FLOOR[name] else None)}
    if row["returncode"] != 0:
        return row
    report = json.loads((capture / "calibration" / "report.json").read_text())
    calibrated = load_rig("anipose", capture / "calibration" / "calibration.toml")
    scores = score_rig(calibrated, rig)
    if not WITH_FLOOR[name]:  # the world is the first camera's frame: only the aligned figures mean anything
        scores |= {"centre_mm": None, "rotation_deg": None, "floor_tilt_deg": None}
    return row | {"rms_px": report["rig"]["rms_px"], "intrinsic_rms_px": max(c["rms_px"] for c in
                                                                            report["cameras"].values()),
                  "board_poses": report["rig"]["board_poses"], **scores, "capture": str(capture)}


def _phone_scenario(captures: Path, out: Path) -> dict:
    camera = phone_camera()
    rig = Rig((camera,))
    recipe = {"board": PHONE_BOARD, "views": PHONE_VIEWS, "seed": 5, "camera": camera.K.tolist(),
              "generator": generator_version()}
    boards = _recording(captures, "calibration-phone", recipe, lambda path: write_board_recording(
        rig, parse_board(PHONE_BOARD), path, intrinsic_views=PHONE_VIEWS, extrinsic_views=0, floor_views=0, seed=5))
    capture = out / "calibration" / "phone"
    row = {"scenario": "phone", "board": PHONE_BOARD, "cameras": 1, "size": "1088x1920",
           "views": f"{PHONE_VIEWS}, intrinsics only", **_calibrate(boards, PHONE_BOARD, capture, None)}
    if row["returncode"] != 0:
        return row
    report = json.loads((capture / "calibration" / "report.json").read_text())["cameras"]["phone"]
    K = np.array(report["K"])
    return row | {"intrinsic_rms_px": report["rms_px"],
                  "focal_percent": float(100 * np.max(np.abs(np.diag(K)[:2] / np.diag(camera.K)[:2] - 1))),
                  "principal_px": float(np.linalg.norm(K[:2, 2] - camera.K[:2, 2]))}


def _taekwondo_copy(folder: Path, calibration: Path | None, frames: int | None) -> Path:
    """A capture made of the bundled taekwondo's media (linked) with its own or another calibration."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for part in ("videos", "background", "groundtruth"):
        (folder / part).symlink_to(TAEKWONDO / part)
    text = (TAEKWONDO / "capture.yaml").read_text()
    if calibration is None:  # copied, not linked: a calibration must lie inside its capture
        shutil.copytree(TAEKWONDO / "calibration", folder / "calibration")
    else:
        shutil.copytree(calibration, folder / "calibration")
        from pipeline.commands.calibrate import calibration_block, update_capture_yaml

        (folder / "capture.yaml").write_text(text)
        text = update_capture_yaml(folder / "capture.yaml", calibration_block(floor=True))
    if frames is not None:
        text = text.replace("stop: null", f"stop: {frames}")
    (folder / "capture.yaml").write_text(text)
    return folder


def _taekwondo_scenario(out: Path, calibrated: Path, *, quick: bool, workers: int) -> dict:
    frames = QUICK_FRAMES if quick else None
    row = {"scenario": "taekwondo"}
    for label, calibration in (("true", None), ("self", calibrated / "calibration")):
        capture = _taekwondo_copy(out / "calibration" / f"taekwondo-{label}-capture", calibration, frames)
        run_out = out / "calibration" / f"taekwondo-{label}"
        measure = run_pipeline(capture, run_out, workers=workers, frames=frames or 112, fresh=True)
        row[f"{label}_run"] = measure.to_dict()
        if measure.ok:
            row[f"{label}_mpjpe_mm"] = evaluate_run(run_out)["mpjpe_mm"]
    if "true_mpjpe_mm" in row and "self_mpjpe_mm" in row:
        row["mpjpe_difference_mm"] = row["self_mpjpe_mm"] - row["true_mpjpe_mm"]
    return row


def run_calibration(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """The suite's section of results.json: one row per scenario (module docstring)."""
    rig = load_rig("colmap", TAEKWONDO / "calibration" / "colmap")
    rows = [_board_scenario(name, captures, out, rig, quick) for name in BOARDS]
    rows.append(_phone_scenario(captures, out))
    if rows[0]["returncode"] == 0:
        rows.append(_taekwondo_scenario(out, Path(rows[0]["capture"]), quick=quick, workers=workers))
    return {"rows": rows}


def board_rows(section: dict) -> list[dict]:
    """The rig scenarios that calibrated (checkerboard, charuco)."""
    return [row for row in section["rows"] if row["scenario"] in BOARDS and row.get("returncode") == 0]


def row_of(section: dict, scenario: str) -> dict:
    return next(row for row in section["rows"] if row["scenario"] == scenario)


COLUMNS = (("scenario", "scenario"), ("board", "board"), ("views", "views"), ("focal %", "focal_percent"),
           ("pp px", "principal_px"), ("centre mm", "centre_mm"), ("rot. °", "rotation_deg"),
           ("aligned centre mm", "aligned_centre_mm"), ("aligned rot. °", "aligned_rotation_deg"),
           ("floor tilt °", "floor_tilt_deg"), ("rig RMS px", "rms_px"), ("lens RMS px", "intrinsic_rms_px"),
           ("command s", "seconds"))

CALIBRATION_NOTES = (
    "How: board recordings rendered by `pipeline.lab.synth.boards` (a printed board on a white card, ray-traced "
    "through each camera's lens into the synthetic studio, exposure, blur, noise 2 grey levels), calibrated by "
    "`python -m pipeline calibrate` and compared with the rig they were rendered with. Errors are the worst "
    "camera's: focal length (fx and fy), principal point, camera centre and rotation as written (the world set by "
    "the boards on the floor against the true world) and after the rigid motion that best aligns the camera "
    "centres; floor tilt = the angle between the calibrated and the true vertical. Rig RMS is the reprojection "
    "error after the bundle adjustment, lens RMS the worst camera's from its intrinsics. The taekwondo row runs "
    "the bundled capture on its true calibration and on the checkerboard row's.")


def _cell(value) -> str | None:
    """Numbers with three significant decimals' worth (errors are small), text as it is, missing as None."""
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"
    return value


def format_calibration(section: dict) -> str:
    rows = [tuple(_cell(row.get(key)) for _, key in COLUMNS)
            for row in section["rows"] if row["scenario"] != "taekwondo"]
    lines = [format_table([header for header, _ in COLUMNS], rows)]
    for row in section["rows"]:
        if row["scenario"] != "taekwondo" and row.get("returncode") != 0:
            lines += ["", f"`{row['scenario']}` failed: {row.get('log_tail', '')}"]
    taekwondo = next((row for row in section["rows"] if row["scenario"] == "taekwondo"), None)
    if taekwondo is not None and "mpjpe_difference_mm" in taekwondo:
        lines += ["", f"taekwondo: MPJPE {taekwondo['true_mpjpe_mm']:.1f} mm on the true calibration, "
                      f"{taekwondo['self_mpjpe_mm']:.1f} mm on the self-calibrated rig "
                      f"({taekwondo['mpjpe_difference_mm']:+.1f} mm)."]
    return "\n".join(lines)
