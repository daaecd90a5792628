"""The command line: end to end through the calibration stage, and one test per user mistake.

Every mistake must be one line ``error: <file or argument>: <what> (expected ...)`` on stderr, exit
status 2, no traceback, and no result written.
"""

from __future__ import annotations

import errno
import importlib
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import make_capture, tiny_rig, write_config, write_video

from calib.errors import InputError
from calib.formats import load_rig
from pipeline.cli import INTERRUPTED, SUBCOMMANDS, main
from pipeline.engine.output_folder import output_lock
from pipeline.graph import STAGES
from pipeline.io import atomic, frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import MANIFEST, WARNINGS_FILE

REPO = Path(__file__).resolve().parents[2]


def run_cli(*argv) -> int:
    return main([str(arg) for arg in argv])


def stage_actions(stdout: str) -> dict[str, str]:
    """Stage name -> action ("ran", "up to date", ...) from the run summary table."""
    names = [stage.name for stage in STAGES]
    rows = [line.split(None, 1) for line in stdout.splitlines() if line.split(None, 1)[:1] and
            line.split()[0] in names]
    return {name: re.split(r"\s{2,}|\s+\d", rest.strip())[0] for name, rest in rows}


def test_run_end_to_end(tiny_capture, tmp_path):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "pipeline", "run", str(tiny_capture), "--out", str(out), "-q"]
    first = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    assert set(stage_actions(first.stdout).values()) == {"ran"}
    assert len(stage_actions(first.stdout)) == len(STAGES)

    rig = load_rig("anipose", out / "calibration" / "rig.toml")
    np.testing.assert_allclose(rig.centres, tiny_rig().centres, atol=1e-9)
    summary = frames_io.read_json(out / "calibration" / "capture.json")
    assert summary["fps"] == 25.0 and summary["frames"] == [0, 1, 2, 3]
    assert summary["cameras"] == ["cam0", "cam1", "cam2"] and summary["height_m"] is None
    assert np.asarray(summary["volume"]).shape == (2, 3)

    second = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0 and set(stage_actions(second.stdout).values()) == {"up to date"}

    status = subprocess.run([sys.executable, "-m", "pipeline", "stages", str(out)], cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert status.returncode == 0
    assert status.stdout.split() == [word for stage in STAGES for word in (stage.name, "up", "to", "date")]


def test_calibration_reruns_when_the_capture_changes(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli("run", tiny_capture, "--out", out, "-q") == 0
    write_config(tiny_capture, subject={"height_m": 1.8})
    assert run_cli("stages", out) == 0
    assert re.search(r"calibration\s+stale: capture config changed", capsys.readouterr().out)
    assert run_cli("run", tiny_capture, "--out", out, "-q") == 0
    assert stage_actions(capsys.readouterr().out)["calibration"] == "ran"
    assert frames_io.read_json(out / "calibration" / "capture.json")["height_m"] == 1.8


def test_help_everywhere(capsys):
    for argv in (["--help"], *([name, "--help"] for name in SUBCOMMANDS)):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 0
        assert "usage:" in capsys.readouterr().out


def test_the_help_listing_summarises_every_subcommand_without_importing_them():
    """`python -m pipeline --help` reads each subcommand's summary from its source: importing them all would load
    open3d, matplotlib and numba, seconds before a dozen lines appear. Nor does finding a source import the
    packages above it (the synthetic renderer above `pipeline.lab.synth.cli`, and scipy with it)."""
    script = textwrap.dedent("""
        import contextlib, io, sys
        from pipeline.cli import main
        with contextlib.redirect_stdout(io.StringIO()) as out:
            try:
                main(["--help"])
            except SystemExit:
                pass
        print(sorted(name for name in ("open3d", "matplotlib", "numba", "scipy", "pipeline.graph", "pipeline.lab.synth")
                     if name in sys.modules))
        print(out.getvalue())
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[2])
    loaded, listing = done.stdout.split("\n", 1)
    assert loaded == "[]"
    words = " ".join(listing.split())  # argparse wraps the summaries
    for name, module_path in SUBCOMMANDS.items():
        summary = importlib.import_module(module_path).__doc__.strip().splitlines()[0]
        assert f" {name} {' '.join(summary.split())}" in words, name


def test_a_closed_pipe_ends_quietly(monkeypatch, tmp_path):
    """`python -m pipeline eval runs/x | head -1`: the reader leaves early, the command ends without a traceback."""
    def broken(args):
        raise BrokenPipeError
    module = types.ModuleType("closes_the_pipe")
    module.add_arguments, module.main = (lambda parser: None), broken
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(SUBCOMMANDS, "eval", module.__name__)
    with open(tmp_path / "stdout", "w") as stdout:
        monkeypatch.setattr(sys, "stdout", stdout)
        assert main(["eval"]) == 0


@pytest.mark.parametrize("hint", ["; the same command resumes", None])
def test_ctrl_c_ends_with_one_line_and_status_130(monkeypatch, capsys, hint):
    def interrupted(args):
        raise KeyboardInterrupt
    module = types.ModuleType("interrupted_by_the_user")
    module.add_arguments, module.main = (lambda parser: None), interrupted
    if hint is not None:
        module.INTERRUPTED_HINT = hint
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(SUBCOMMANDS, "eval", module.__name__)
    assert main(["eval"]) == INTERRUPTED == 130
    assert capsys.readouterr().err.splitlines() == [f"interrupted{hint or ''}"]


def test_the_commands_a_rerun_resumes_say_so_after_ctrl_c():
    for name in ("run", "batch"):
        assert "resumes" in importlib.import_module(SUBCOMMANDS[name]).INTERRUPTED_HINT


# ---------------------------------------------------------------------------------------------
# Bad input: one test per mistake


def expect_error(capsys, argv, *fragments, out: Path | None = None) -> str:
    """Run the CLI, check exit status 2 and a one-line message containing ``fragments``."""
    assert run_cli(*argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    message = err[-1]
    assert message.startswith("error: ") and "Traceback" not in "\n".join(err)
    assert "expected" in message.lower()
    for fragment in fragments:
        assert fragment in message, message
    if out is not None:
        assert not list(out.rglob(MANIFEST)), "a failed run left a manifest behind"
    return message


def run_argv(capture: Path, out: Path, *extra) -> list:
    return ["run", capture, "--out", out, "-q", *extra]


def test_missing_capture_yaml(tiny_capture, tmp_path, capsys):
    (tiny_capture / "capture.yaml").unlink()
    out = tmp_path / "out"
    expect_error(capsys, run_argv(tiny_capture, out), "capture.yaml: missing")
    assert not out.exists()


def test_malformed_capture_yaml(tiny_capture, tmp_path, capsys):
    (tiny_capture / "capture.yaml").write_text("fps: [25\ncalibration: {")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "capture.yaml: not valid YAML",
                 "at line 2, column 12")


def test_a_tolerance_leaving_one_view_to_agree_is_refused_before_any_work(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    expect_error(capsys, run_argv(tiny_capture, out, "--set", "reconstruction.tolerated_views=2"),
                 "reconstruction.tolerated_views=2: the rig has 3 cameras (expected at most 1")
    assert not out.exists()


def test_capture_yaml_not_a_mapping(tiny_capture, tmp_path, capsys):
    (tiny_capture / "capture.yaml").write_text("- fps\n- 25\n")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "capture.yaml: top level is list")


def test_bad_fps(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, fps=-3)
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "capture.yaml: fps is -3", "positive")


def test_unknown_calibration_format(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, calibration={"format": "blender", "path": "calibration/calibration.toml"})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"),
                 "calibration.format 'blender' is unknown", "colmap, opencv, anipose")


def test_calibration_path_missing(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, calibration={"format": "anipose", "path": "calib/nowhere.toml"})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "calibration.path 'calib/nowhere.toml'")


def test_calibration_file_unreadable(tiny_capture, tmp_path, capsys):
    (tiny_capture / "calibration" / "calibration.toml").write_text("[cam_0\nname = ")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "calibration.toml", "TOML")


def test_camera_in_media_but_not_in_calibration(tiny_capture, tmp_path, capsys):
    shutil.copytree(tiny_capture / "images" / "cam0", tiny_capture / "images" / "cam9")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"),
                 "images: camera 'cam9' is not in the calibration")


def test_camera_in_calibration_but_not_in_media(tiny_capture, tmp_path, capsys):
    shutil.rmtree(tiny_capture / "images" / "cam1")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"),
                 "images: calibrated camera 'cam1' has no media")


def test_videos_with_different_frame_counts(tmp_path, capsys):
    """Refused, saying how to keep the frames every camera has; a frames.stop within them is that choice, and one
    beyond them is refused too."""
    capture = make_capture(tmp_path / "c", media="videos", n_frames=6)
    write_video(capture / "videos" / "cam2.avi", 5)
    expect_error(capsys, run_argv(capture, tmp_path / "out"), "cam2.avi: 5 frames but cam0.avi has 6",
                 "frames: {stop: 5} in capture.yaml")
    write_config(capture, frames={"start": 0, "stop": 5, "step": 1})
    assert Capture.open(capture).frame_numbers == (0, 1, 2, 3, 4)
    write_config(capture, frames={"start": 1, "stop": 4, "step": 2})
    assert Capture.open(capture).frame_numbers == (1, 3)
    write_config(capture, frames={"start": 0, "stop": 6, "step": 1})
    expect_error(capsys, run_argv(capture, tmp_path / "out"), "cam2.avi: 5 frames but cam0.avi has 6")


def test_image_folders_with_different_frames(tiny_capture, tmp_path, capsys):
    (tiny_capture / "images" / "cam2" / "000003.png").unlink()
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "frame 3", "same frame numbers",
                 "frames.start and frames.stop")
    write_config(tiny_capture, frames={"start": 0, "stop": 3, "step": 1})
    assert Capture.open(tiny_capture).frame_numbers == (0, 1, 2)


def test_non_image_file_in_an_image_folder(tiny_capture, tmp_path, capsys):
    (tiny_capture / "images" / "cam0" / "notes.txt").write_text("hello")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "notes.txt: not a frame image")


def test_unreadable_image(tiny_capture, tmp_path, capsys):
    (tiny_capture / "images" / "cam1" / "000000.png").write_bytes(b"not a png")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "000000.png: not a readable image")


def test_image_size_differs_from_calibration(tmp_path, capsys):
    capture = make_capture(tmp_path / "c")
    make_capture(tmp_path / "other", size=(80, 60))
    shutil.rmtree(capture / "images")
    shutil.copytree(tmp_path / "other" / "images", capture / "images")
    expect_error(capsys, run_argv(capture, tmp_path / "out"), "64x48", "80x60")


def test_unknown_stage_name(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    expect_error(capsys, run_argv(tiny_capture, out, "--only", "tracknig"),
                 "--only tracknig: unknown stage", "calibration")
    assert not out.exists()


def test_set_unknown_stage(tiny_capture, tmp_path, capsys):
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out", "--set", "silhouetes.threshold=3"),
                 "--set silhouetes: unknown stage", "calibration")


def test_set_key_of_a_stage_without_parameters(tiny_capture, tmp_path, capsys):
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out", "--set", "calibration.scale=2"),
                 "--set calibration: this stage takes no parameters")


def test_set_malformed(tiny_capture, tmp_path, capsys):
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out", "--set", "threshold"),
                 "--set threshold: malformed", "stage.param=value")


def test_config_file_missing(tiny_capture, tmp_path, capsys):
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out", "--config", tmp_path / "params.yaml"),
                 "params.yaml: cannot read")


def test_frames_start_out_of_range(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, frames={"start": 10})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "frames.start 10 is out of range", "3")


def test_frames_stop_out_of_range(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, frames={"start": 0, "stop": 9})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "frames.stop 9 is out of range")


def test_frames_step_not_positive(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, frames={"step": 0})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "frames.step is 0", ">= 1")


def test_unknown_units(tiny_capture, tmp_path, capsys):
    config = yaml.safe_load((tiny_capture / "capture.yaml").read_text())
    write_config(tiny_capture, calibration={**config["calibration"], "units": "inch"})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"),
                 "calibration.units 'inch' is unknown", "m, cm, mm")


def test_unknown_up_axis(tiny_capture, tmp_path, capsys):
    config = yaml.safe_load((tiny_capture / "capture.yaml").read_text())
    write_config(tiny_capture, calibration={**config["calibration"], "up": "z"})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "calibration.up 'z' is unknown", "+z")


def test_volume_min_not_below_max(tiny_capture, tmp_path, capsys):
    write_config(tiny_capture, volume={"min": [0, 0, 0], "max": [1, -1, 2]})
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "volume.min", "min < max")


def test_no_media(tiny_capture, tmp_path, capsys):
    shutil.rmtree(tiny_capture / "images")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "no media found")


def test_capture_directory_missing(tmp_path, capsys):
    expect_error(capsys, run_argv(tmp_path / "nothing", tmp_path / "out"), "no such capture directory")


def test_concurrent_run_on_the_same_output(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    with output_lock(out):
        expect_error(capsys, run_argv(tiny_capture, out), "another run is using this output directory",
                     out=out)


def test_stages_of_a_folder_that_was_never_run(tmp_path, capsys):
    expect_error(capsys, ["stages", tmp_path], "run.json: missing")


def test_failed_rerun_leaves_no_stale_result(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    os.remove(tiny_capture / "images" / "cam0" / "000002.png")
    expect_error(capsys, run_argv(tiny_capture, out), "same frame numbers")
    assert (out / "calibration" / MANIFEST).exists()  # validation failed before touching the results


@pytest.mark.parametrize("where", ["capture", "inside", "around"])
def test_an_output_folder_overlapping_the_capture_is_refused_untouched(tiny_capture, capsys, where):
    out = {"capture": tiny_capture, "inside": tiny_capture / "runs", "around": tiny_capture.parent}[where]
    before = sorted(path.relative_to(tiny_capture) for path in tiny_capture.rglob("*"))
    expect_error(capsys, run_argv(tiny_capture, out), f"--out {out}: overlaps the capture")
    assert sorted(path.relative_to(tiny_capture) for path in tiny_capture.rglob("*")) == before


def result_files(out: Path) -> dict[str, bytes]:
    """Every result file of an output folder by relative path (manifests, the lock and the log of warnings left
    out)."""
    return {path.relative_to(out).as_posix(): path.read_bytes() for path in sorted(out.rglob("*"))
            if path.is_file() and path.name not in (MANIFEST, ".lock", WARNINGS_FILE)}


def test_damaged_results_are_recomputed_as_they_were(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    before = result_files(out)
    ply = out / "reconstruction" / "000001.ply"
    data = bytearray(ply.read_bytes())
    data[-20] ^= 0x40  # a coordinate, same size
    ply.write_bytes(bytes(data))
    mask = out / "silhouettes" / "cam1" / "000002.png"
    mask.write_bytes(mask.read_bytes()[:-5])  # truncated
    record = out / "tracking" / "frames" / "000002.json"
    text = record.read_text()
    digit = text.index('"log_likelihood": ') + 20
    record.write_text(text[:digit] + ("1" if text[digit] != "1" else "2") + text[digit + 1:])
    capsys.readouterr()
    assert run_cli("stages", out) == 0
    status = capsys.readouterr().out
    for stage, name in (("silhouettes", "cam1/000002.png"), ("reconstruction", "000001.ply"),
                        ("tracking", "frames/000002.json")):
        assert re.search(rf"{stage}\s+stale: output files changed on disk: 1 damaged \({name}\)", status), status
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    assert stage_actions(capsys.readouterr().out) == {
        "calibration": "up to date", "silhouettes": "ran", "reconstruction": "ran", "tracking": "ran",
        "export": "up to date"}  # the same files again, so the export stays valid
    assert result_files(out) == before


def test_a_damaged_file_of_the_capture_is_a_one_line_error(tmp_path, capsys):
    capture = make_capture(tmp_path / "c", media="none", silhouettes=True)
    mask = capture / "silhouettes" / "cam0" / "000001.png"
    mask.write_bytes(mask.read_bytes()[:-5])
    expect_error(capsys, run_argv(capture, tmp_path / "out"), f"{mask}: PNG file is truncated")


@pytest.mark.parametrize("below", ["", "results"])
def test_out_where_a_file_is(tiny_capture, tmp_path, capsys, below):
    in_the_way = tmp_path / "notes.txt"
    in_the_way.write_text("mine")
    expect_error(capsys, run_argv(tiny_capture, in_the_way / below), f"{in_the_way} is a file, not a folder")
    assert in_the_way.read_text() == "mine"


def test_out_on_a_read_only_file_system(tiny_capture, tmp_path, capsys, monkeypatch):
    read_only, make_folder = tmp_path / "mounted", Path.mkdir

    def mkdir(path, *args, **kwargs):
        if read_only in (path, *path.parents):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        make_folder(path, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    expect_error(capsys, run_argv(tiny_capture, read_only / "out"), "Read-only file system",
                 "on a file system that can be written")


def test_a_full_disk_is_a_one_line_error_and_the_next_run_resumes(tiny_capture, tmp_path, capsys, monkeypatch):
    out, write, calls = tmp_path / "out", atomic.write_bytes, []

    def full_after_some_files(path, data):
        calls.append(path)
        if len(calls) > 12:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write(path, data)

    monkeypatch.setattr(atomic, "write_bytes", full_after_some_files)
    expect_error(capsys, run_argv(tiny_capture, out), "No space left on device", "free space")
    monkeypatch.setattr(atomic, "write_bytes", write)
    assert run_cli(*run_argv(tiny_capture, out)) == 0


def test_a_file_too_large_in_a_worker_process_is_a_one_line_error(tiny_capture, tmp_path):
    """Files over 6 kB fail (ulimit -f): the reconstruction's clouds, written in the pool's processes."""
    def small_files_only():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # an error from write(), not the signal's kill
        resource.setrlimit(resource.RLIMIT_FSIZE, (6000, 6000))

    command = [sys.executable, "-m", "pipeline", "run", str(tiny_capture), "--out", str(tmp_path / "out"), "-q",
               "--workers", "2"]
    result = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300,
                            preexec_fn=small_files_only)
    assert result.returncode == 2, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert re.fullmatch(rf"error: {tmp_path / 'out' / 'reconstruction'}/\d{{6}}\.ply: File too large "
                        r"\(expected files allowed to grow that large \(see ulimit -f\)\)", last), last


@pytest.mark.parametrize("where", ["inside", "elsewhere"])
def test_an_absolute_calibration_path_is_read(tmp_path, capsys, where):
    """Inside the capture as it is; outside it only with --allow-outside-paths, which `stages` remembers."""
    capture, out = make_capture(tmp_path / "c"), tmp_path / "out"
    calibration = (make_capture(tmp_path / "other") if where == "elsewhere" else capture) / "calibration"
    write_config(capture, calibration={"format": "anipose", "path": str(calibration / "calibration.toml")})
    flag = ("--allow-outside-paths",) if where == "elsewhere" else ()
    assert run_cli(*run_argv(capture, out, "--to", "calibration", *flag)) == 0
    assert run_cli("stages", out) == 0
    assert re.search(r"calibration\s+up to date", capsys.readouterr().out)


@pytest.mark.parametrize("path", ["../../../../../../etc/passwd", "/etc/passwd", "linked/calibration.toml"])
def test_a_calibration_path_leading_outside_the_capture_is_refused(tmp_path, capsys, path):
    capture = make_capture(tmp_path / "c")
    (capture / "linked").symlink_to(make_capture(tmp_path / "other") / "calibration")
    write_config(capture, calibration={"format": "anipose", "path": path})
    expect_error(capsys, run_argv(capture, tmp_path / "out"), f"calibration.path {path!r} leads outside the capture",
                 "--allow-outside-paths")


def test_yaml_aliases_are_refused_before_they_expand(tiny_capture, tmp_path, capsys):
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{depth}: &a{depth} [{', '.join([f'*a{depth - 1}'] * 9)}]" for depth in range(1, 10)]
    text = (tiny_capture / "capture.yaml").read_text() + "subject:\n  " + "\n  ".join(lines) + "\n"
    (tiny_capture / "capture.yaml").write_text(text)  # 9^10 strings once expanded
    started = time.perf_counter()
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"), "capture.yaml: line ", "alias *a0")
    assert time.perf_counter() - started < 5
    (tmp_path / "params.yaml").write_text("tracking: &t {}\nexport: *t\n")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out", "--config", tmp_path / "params.yaml"),
                 "params.yaml: line 2: alias *t")


def test_a_failed_rerun_marks_what_it_left_incomplete(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    (tiny_capture / "images" / "cam1" / "000002.png").write_bytes(b"not a png")  # read only by the stage
    expect_error(capsys, run_argv(tiny_capture, out), "000002.png: not a readable image")
    assert [path.parent.name for path in out.rglob(MANIFEST)] == ["calibration"]
    # The silhouettes keep the frames they wrote, to resume from; what was made from the old ones is gone.
    assert (out / "silhouettes").is_dir()
    assert not any((out / stage).exists() for stage in ("reconstruction", "tracking", "export"))
    assert not (out / ".lock").exists()
    assert run_cli("stages", out) == 0
    status = capsys.readouterr().out
    assert re.search(r"silhouettes\s+incomplete", status) and "the last run failed: " in status
    assert "000002.png: not a readable image" in status.splitlines()[-1]


def test_eval_refuses_the_joints_of_an_unfinished_export(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    (out / "export" / MANIFEST).unlink()  # what a run killed while it rewrote the export leaves
    expect_error(capsys, ["eval", str(out), "--truth", str(tiny_capture / "groundtruth" / "joints.csv")],
                 "export/manifest.json: missing, the last run did not finish its export")


def test_a_fresh_output_folder_is_gone_after_a_run_refused_at_once(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    expect_error(capsys, run_argv(tiny_capture, out, "--only", "tracking"), "needs the results of calibration")
    assert not out.exists()


def test_camera_names_from_files_are_echoed_escaped(tmp_path, capsys):
    capture = make_capture(tmp_path / "c")
    toml = capture / "calibration" / "calibration.toml"
    toml.write_text(toml.read_text().replace('name = "cam1"', 'name = "cam1\\u001b]0;owned\\u0007\\u001b[2J"'))
    assert run_cli(*run_argv(capture, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\x07" not in err
    assert "cam1\\x1b]0;owned\\x07\\x1b[2J" in err.splitlines()[-1]


def test_an_empty_capture_yaml_says_what_it_must_hold(tiny_capture, tmp_path, capsys):
    (tiny_capture / "capture.yaml").write_text("# nothing yet\n")
    expect_error(capsys, run_argv(tiny_capture, tmp_path / "out"),
                 "capture.yaml: empty (expected a mapping with at least fps and calibration")


def test_the_examples_given_to_users_name_real_parameters():
    """run --help, the --set error and the params module's docstring show parameters that exist."""
    import pipeline.commands.run as run_command
    from pipeline.engine import params as params_module
    from pipeline.engine.params import apply_overrides, default_params, parse_assignments

    examples = re.findall(r"--set (\S+=\S+)", run_command.__doc__)
    with pytest.raises(InputError) as malformed:
        parse_assignments(["threshold"])
    examples += re.findall(r"e\.g\. (\S+=[^)\s]+)", str(malformed.value))
    assert len(examples) == 2
    apply_overrides(default_params(STAGES), parse_assignments(examples), source="example")
    block = params_module.__doc__.split("::", 1)[1].split("\n\n")[1]
    apply_overrides(default_params(STAGES), yaml.safe_load(textwrap.dedent(block)), source="docstring")


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_make_lists_only_the_sample_folders():
    result = subprocess.run(["make", "-s", "check-seq", "SEQ=nonexistent"], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2
    listed = result.stdout.split("available: ")[1].split()
    assert listed == sorted(path.name for path in (REPO / "data_samples").iterdir() if path.is_dir())
    assert "README.md" not in listed


def test_a_run_whose_result_is_not_usable_exits_3_with_one_line(tmp_path):
    from pipeline.commands.run import UNUSABLE_RESULT, unusable_result

    export = tmp_path / "export"
    export.mkdir()
    lines = ["frame,joint,x,y,z"] + [f"{frame},pelvis,0,0,1" for frame in range(4)]
    (export / "joints.csv").write_text("\n".join(lines) + "\n")
    assert "no motion.bvh, joints.c3d written" in unusable_result(export, 4)
    (export / "motion.bvh").write_text("HIERARCHY\n")
    (export / "joints.c3d").write_bytes(b"c3d")
    assert unusable_result(export, 8) is None  # half of the frames is enough
    problem = unusable_result(export, 10)
    assert "joints.csv: only 4 of 10 frames estimated" in problem and "\n" not in problem
    assert UNUSABLE_RESULT == 3
    (export / "joints.csv").write_text("frame,joint,x,y,z\n")  # the export of a run that lost every frame
    assert "joints.csv: no frame estimated" in unusable_result(export, 10)


def test_a_file_the_user_put_in_a_stage_folder_is_never_deleted(tiny_capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    notes = out / "export" / "notes.txt"
    notes.write_text("mine")
    expect_error(capsys, run_argv(tiny_capture, out, "--set", "export.bvh_units=m"),
                 "export/notes.txt: not written by the pipeline (1 such file(s) in export/)", "move it out")
    assert notes.read_text() == "mine"
    notes.rename(tmp_path / "notes.txt")
    assert run_cli(*run_argv(tiny_capture, out, "--set", "export.bvh_units=m")) == 0


@pytest.mark.parametrize("name", ["run.json", "warnings.json"])
def test_a_users_file_named_like_the_runs_own_record_is_not_overwritten(tiny_capture, tmp_path, capsys, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text('{"my": "own"}')
    expect_error(capsys, run_argv(tiny_capture, out), f"{name}: not written by the pipeline")
    assert (out / name).read_text() == '{"my": "own"}'
    (out / name).unlink()
    assert run_cli(*run_argv(tiny_capture, out)) == 0
    assert run_cli(*run_argv(tiny_capture, out)) == 0  # its own files pass
