"""Replay issue #13's battery on the tiny sample and print the counts, so a change is checked in one command.

Four categories, each case a subprocess ``python -m pipeline run ...`` with a timeout, on a copy of
``data_samples/tiny`` in a work folder:

- ``bad input``: a broken capture, calibration, parameter or output folder must exit with status 2 and
  one stderr line naming the file or parameter, no traceback, and leave every user file byte-identical;
- ``kill``: a run killed (SIGKILL, whole process group) after a seeded random delay, then rerun, must
  end with the uninterrupted run's ``joints.csv`` and no temporary files;
- ``corruption``: a finished run's per-frame output or manifest truncated or flipped, then rerun, must be
  recomputed (exit 0, the damaged file and ``joints.csv`` as they were);
- ``concurrency``: two runs on one ``--out`` at once: one proceeds, the other refuses in one line.

Usage::

    .venv/bin/python scripts/reliability.py [--out DIR] [--seed N] [--quick]

Exit status 1 when any check fails (the failing cases are listed under the table), 0 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "data_samples" / "tiny"
TIMEOUT_S = 120
TEMP_PREFIX = ".tmp-"  # pipeline.io.atomic.TEMP_PREFIX; not imported so the script runs without the package
CATEGORIES = ("bad input", "kill", "corruption", "concurrency")


@dataclass
class Outcome:
    """What one case found; a case passes when ``problems`` stays empty.

    The counters are kept apart from the problem text because the table reports them per category:
    a traceback or a silent success is a different defect from a wrong message.
    """

    category: str
    name: str
    problems: list[str] = field(default_factory=list)
    tracebacks: int = 0
    silent_successes: int = 0
    user_files_changed: int = 0
    unrecomputed: int = 0

    @property
    def passed(self) -> bool:
        return not self.problems


@dataclass
class BadInput:
    """One user mistake: ``prepare`` breaks a fresh capture copy and returns the ``run`` arguments.

    ``names`` is the file or parameter the one-line message must mention, so that a message which
    is merely short (``error: invalid value``) does not count as telling the user what to fix.
    """

    name: str
    names: str
    prepare: Callable[[Path, Path], list[str]]


@dataclass
class Corruption:
    """One damage to a finished run: ``path`` relative to the output folder, ``how`` truncate or flip."""

    path: str
    how: str


# --------------------------------------------------------------------------- running the pipeline


def pipeline_run(argv: list[str], timeout: float = TIMEOUT_S) -> subprocess.CompletedProcess:
    """Run ``python -m pipeline run`` as a user would, in its own process; a hang counts as a failure.

    Returns
    -------
    subprocess.CompletedProcess
        With ``returncode`` -9 and the text ``timed out`` on stderr when the run did not end in time.
    """
    command = [sys.executable, "-m", "pipeline", "run", *argv]
    try:
        return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return subprocess.CompletedProcess(command, -9, "", f"timed out after {timeout:.0f} s")


def standard(capture: Path, work: Path, *extra: str) -> list[str]:
    """The arguments of an ordinary run of ``capture`` into ``work/out`` (one process: errors surface first)."""
    return [str(capture), "--out", str(work / "out"), "-q", "--workers", "1", *extra]


def tree_hashes(root: Path, skip: Path | None = None) -> dict[str, str]:
    """SHA-256 of every file under ``root`` (``skip``'s subtree left out): the user's files, to compare."""
    return {path.relative_to(root).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(root.rglob("*"))
            if path.is_file() and (skip is None or skip not in path.parents)}


def fresh_capture(work: Path) -> Path:
    """A private copy of the tiny sample, so a case may break it freely."""
    capture = work / "capture"
    shutil.copytree(SAMPLE, capture)
    return capture


def traceback_in(result: subprocess.CompletedProcess) -> bool:
    return "Traceback (most recent call last)" in result.stderr + result.stdout


# --------------------------------------------------------------------------- bad inputs


def edit(path: Path, old: str, new: str, count: int = 1) -> None:
    """Replace text in a user file (regular expression), failing loudly when the sample changed shape."""
    text, done = re.subn(old, new, path.read_text(), count=count, flags=re.MULTILINE)
    if not done:
        raise RuntimeError(f"{path}: pattern {old!r} not found (has the tiny sample changed?)")
    path.write_text(text)


def yaml_of(capture: Path) -> Path:
    return capture / "capture.yaml"


def toml_of(capture: Path) -> Path:
    return capture / "calibration" / "calibration.toml"


def with_yaml(text: str) -> Callable[[Path, Path], list[str]]:
    """A case whose capture.yaml is replaced by ``text``."""
    def prepare(capture: Path, work: Path) -> list[str]:
        yaml_of(capture).write_text(text)
        return standard(capture, work)
    return prepare


def with_yaml_edit(old: str, new: str) -> Callable[[Path, Path], list[str]]:
    """A case whose capture.yaml has ``old`` replaced by ``new``."""
    def prepare(capture: Path, work: Path) -> list[str]:
        edit(yaml_of(capture), old, new)
        return standard(capture, work)
    return prepare


def with_toml_edit(old: str, new: str | Callable, count: int = 1) -> Callable[[Path, Path], list[str]]:
    """A case whose calibration.toml has ``old`` replaced by ``new`` (``count`` = 0: every match)."""
    def prepare(capture: Path, work: Path) -> list[str]:
        edit(toml_of(capture), old, new, count)
        return standard(capture, work)
    return prepare


def with_set(assignment: str) -> Callable[[Path, Path], list[str]]:
    """A case of an untouched capture and one bad ``--set``."""
    return lambda capture, work: standard(capture, work, "--set", assignment)


def with_files(change: Callable[[Path], None]) -> Callable[[Path, Path], list[str]]:
    """A case whose media or masks are changed by ``change(capture)``."""
    def prepare(capture: Path, work: Path) -> list[str]:
        change(capture)
        return standard(capture, work)
    return prepare


def scaled_translations(match: re.Match) -> str:
    """A calibration in millimetres while capture.yaml still says metres."""
    values = [float(value) * 1000 for value in match.group(1).split(",")]
    return "translation = [" + ", ".join(repr(value) for value in values) + "]"


def precomputed_masks_with_an_empty_one(capture: Path) -> None:
    """Precomputed silhouettes (the ground-truth masks) with one file of zero bytes."""
    shutil.copytree(capture / "groundtruth" / "masks", capture / "silhouettes")
    (capture / "silhouettes" / "cam2" / "000003.png").write_bytes(b"")


def garbage_videos(capture: Path) -> None:
    """The image folders replaced by video files that are not videos (one kind of media per capture)."""
    shutil.rmtree(capture / "images")
    (capture / "videos").mkdir()
    for camera in ("cam1", "cam2", "cam3", "cam4"):
        (capture / "videos" / f"{camera}.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 4)


def outside_calibration(capture: Path, work: Path) -> list[str]:
    """calibration.path leading out of the capture (a capture.yaml from elsewhere could name any file)."""
    shutil.copy(toml_of(capture), work / "elsewhere.toml")
    edit(yaml_of(capture), r"path: calibration/calibration.toml", "path: ../elsewhere.toml")
    return standard(capture, work)


def out_is_a_file(capture: Path, work: Path) -> list[str]:
    """--out naming the user's own file, which must survive."""
    (work / "notes.txt").write_text("the user's notes\n")
    return [str(capture), "--out", str(work / "notes.txt"), "-q"]


ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8))

BAD_INPUTS: list[BadInput] = [
    BadInput("capture.yaml missing", "capture.yaml", with_files(lambda c: yaml_of(c).unlink())),
    BadInput("capture.yaml empty", "capture.yaml", with_yaml("")),
    BadInput("capture.yaml garbage", "capture.yaml", with_yaml("fps: [28\n\x00\x01{{: ]]\n")),
    BadInput("capture.yaml a list", "capture.yaml", with_yaml("- fps\n- 28\n")),
    BadInput("unknown top-level key", "volum", with_yaml_edit(r"^volume:", "volum:")),
    BadInput("unknown calibration key", "unit", with_yaml_edit(r"  units: m", "  unit: m")),
    BadInput("YAML alias bomb", "capture.yaml", with_yaml(ALIAS_BOMB)),
    BadInput("fps negative", "fps", with_yaml_edit(r"fps: 28.0", "fps: -28")),
    BadInput("frames.step zero", "step", with_yaml_edit(r"step: 1", "step: 0")),
    BadInput("unknown calibration format", "format", with_yaml_edit(r"format: anipose", "format: opencvv")),
    BadInput("unknown units", "units", with_yaml_edit(r"units: m", "units: furlongs")),
    BadInput("calibration outside the capture", "elsewhere.toml", outside_calibration),
    BadInput("calibration absolute system file", "/etc/hostname",
             with_yaml_edit(r"path: calibration/calibration.toml", "path: /etc/hostname")),
    BadInput("calibration in mm declared m", "calibration.toml",
             with_toml_edit(r"translation = \[([^\]]*)\]", scaled_translations, count=0)),
    BadInput("huge focal length", "calibration.toml", with_toml_edit(r"234\.20341257419813", "2.3e12", count=2)),
    BadInput("NaN in the camera matrix", "calibration.toml", with_toml_edit(r"234\.20341257419813", "nan")),
    BadInput("calibration garbage", "calibration.toml", with_toml_edit(r"\[cam_1\]", "[cam_1\n=\x00")),
    BadInput("camera missing from the media", "cam4", with_files(lambda c: shutil.rmtree(c / "images" / "cam4"))),
    BadInput("camera missing from the calibration", "cam4", with_toml_edit(r"\[cam_3\][\s\S]*", "")),
    BadInput("camera names mismatched", "cam9",
             with_files(lambda c: (c / "images" / "cam4").rename(c / "images" / "cam9"))),
    BadInput("frame-count mismatch", "cam2",
             with_files(lambda c: (c / "images" / "cam2" / "000005.png").unlink())),
    BadInput("empty image file", "000003.png",
             with_files(lambda c: (c / "images" / "cam1" / "000003.png").write_bytes(b""))),
    BadInput("image not an image", "000004.png",
             with_files(lambda c: (c / "images" / "cam3" / "000004.png").write_text("not a png\n"))),
    BadInput("unreadable video", ".mp4", with_files(garbage_videos)),
    BadInput("empty precomputed silhouette", "000003.png", with_files(precomputed_masks_with_an_empty_one)),
    BadInput("background garbage", "cam2.png",
             with_files(lambda c: (c / "background" / "cam2.png").write_bytes(b"\x89PNG\r\n\x1a\n junk"))),
    BadInput("--set silhouettes negative", "silhouettes.strong_threshold",
             with_set("silhouettes.strong_threshold=-1")),
    BadInput("--set silhouettes nan", "silhouettes.weak_threshold", with_set("silhouettes.weak_threshold=nan")),
    BadInput("--set silhouettes wrong type", "silhouettes.downsample", with_set("silhouettes.downsample=two")),
    BadInput("--set silhouettes unknown choice", "silhouettes.shadows", with_set("silhouettes.shadows=sideways")),
    BadInput("--set reconstruction negative", "reconstruction.n_observations",
             with_set("reconstruction.n_observations=-5")),
    BadInput("--set reconstruction nan", "reconstruction.voxel_size_m", with_set("reconstruction.voxel_size_m=nan")),
    BadInput("--set reconstruction unknown choice", "reconstruction.method", with_set("reconstruction.method=mesh")),
    BadInput("--set tracking zero sigma", "tracking.sigma_m", with_set("tracking.sigma_m=0")),
    BadInput("--set tracking wrong type", "tracking.max_iterations", with_set("tracking.max_iterations=ten")),
    BadInput("--set tracking unknown choice", "tracking.distance", with_set("tracking.distance=euclid")),
    BadInput("--set tracking inf", "tracking.height_m", with_set("tracking.height_m=inf")),
    BadInput("--set export wrong type", "export.report", with_set("export.report=maybe")),
    BadInput("--set unknown parameter", "tracking.sigma", with_set("tracking.sigma=0.02")),
    BadInput("--set a stage without parameters", "calibration", with_set("calibration.anything=1")),
    BadInput("--config missing", "nowhere.yaml",
             lambda capture, work: standard(capture, work, "--config", str(work / "nowhere.yaml"))),
    BadInput("--out is the capture", "--out", lambda capture, work: [str(capture), "--out", str(capture), "-q"]),
    BadInput("--out inside the capture", "--out",
             lambda capture, work: [str(capture), "--out", str(capture / "runs"), "-q"]),
    BadInput("--out an existing file", "notes.txt", out_is_a_file),
]
QUICK_BAD_INPUTS = ("YAML alias bomb", "calibration outside the capture", "--set tracking unknown choice")


def replay_bad_input(case: BadInput, root: Path) -> Outcome:
    """Break a fresh capture copy, run, and check the refusal: status 2, one line naming the culprit, files kept.

    Every file of the case's folder (the capture, and any user file next to it) is hashed before and
    after; only ``work/out``, the output folder the run was given, may change.
    """
    work = root / re.sub(r"\W+", "-", case.name).strip("-")
    work.mkdir(parents=True)
    capture = fresh_capture(work)
    argv = case.prepare(capture, work)
    before = tree_hashes(work, skip=work / "out")
    result = pipeline_run(argv)
    after = tree_hashes(work, skip=work / "out")
    outcome = Outcome("bad input", case.name)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    if traceback_in(result):
        outcome.tracebacks = 1
        outcome.problems.append("traceback")
    if result.returncode == 0:
        outcome.silent_successes = 1
        outcome.problems.append("exit 0")
    elif result.returncode != 2:
        outcome.problems.append(f"exit {result.returncode} (expected 2)")
    if len(lines) != 1:
        outcome.problems.append(f"{len(lines)} stderr lines, the first: {lines[0][:120] if lines else ''}")
    elif case.names not in lines[0]:
        outcome.problems.append(f"message does not name {case.names!r}")
    changed = sorted(name for name in before.keys() | after.keys() if before.get(name) != after.get(name))
    if changed:
        outcome.user_files_changed = len(changed)
        outcome.problems.append(f"user files changed: {', '.join(changed[:3])}")
    if outcome.problems and lines:
        outcome.problems.append(f"stderr: {lines[-1][:160]}")
    return outcome


# --------------------------------------------------------------------------- kills, corruptions, concurrency


def full_argv(capture: Path, out: Path) -> list[str]:
    """A whole run with two worker processes, so kills also hit workers mid-frame."""
    return [str(capture), "--out", str(out), "-q", "--workers", "2"]


def leftovers(out: Path) -> list[str]:
    """Temporary files a run left behind (``.tmp-*`` anywhere under the output folder)."""
    return sorted(path.relative_to(out).as_posix() for path in out.rglob(TEMP_PREFIX + "*"))


def check_finished(outcome: Outcome, result: subprocess.CompletedProcess, out: Path, joints: bytes) -> None:
    """A rerun must succeed, leave no temporary file, and give the uninterrupted run's joints.csv."""
    if traceback_in(result):
        outcome.tracebacks += 1
        outcome.problems.append("traceback")
    if result.returncode != 0:
        outcome.problems.append(f"rerun exit {result.returncode}: {result.stderr.strip()[-160:]}")
        return
    if (out / "export" / "joints.csv").read_bytes() != joints:
        outcome.unrecomputed += 1
        outcome.problems.append("joints.csv differs from the uninterrupted run's")
    if leftovers(out):
        outcome.problems.append(f"temporary files left: {', '.join(leftovers(out)[:3])}")


def replay_kill(capture: Path, out: Path, delay: float, joints: bytes) -> Outcome:
    """SIGKILL a run's whole process group after ``delay`` seconds, rerun it, and check the result."""
    outcome = Outcome("kill", f"SIGKILL after {delay:.2f} s")
    process = subprocess.Popen([sys.executable, "-m", "pipeline", "run", *full_argv(capture, out)], cwd=REPO,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    time.sleep(delay)
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGKILL)
    else:  # nothing was interrupted: the case would pass without testing a resume
        outcome.problems.append("the run had finished before the kill")
    process.wait()
    check_finished(outcome, pipeline_run(full_argv(capture, out)), out, joints)
    return outcome


def damage(path: Path, how: str, rng: random.Random) -> None:
    """Truncate a file to a seeded fraction of its length, or flip one seeded byte of it (same size)."""
    data = bytearray(path.read_bytes())
    if how == "truncate":
        path.write_bytes(bytes(data[: rng.randrange(len(data))]))
        return
    position = rng.randrange(len(data))
    data[position] ^= 1 << rng.randrange(7)  # low bits: the byte stays printable in a text file more often
    path.write_bytes(bytes(data))


def replay_corruption(capture: Path, finished: Path, out: Path, case: Corruption, rng: random.Random) -> Outcome:
    """Damage one file of a copy of a finished run, rerun, and check it was recomputed as it was.

    A manifest is bookkeeping with times in it, so for one only the rerun's success and the final
    joints.csv are compared; any other file must come back byte-identical.
    """
    outcome = Outcome("corruption", f"{case.how} {case.path}")
    shutil.copytree(finished, out)
    target = out / case.path
    original = target.read_bytes()
    damage(target, case.how, rng)
    result = pipeline_run(full_argv(capture, out))
    check_finished(outcome, result, out, (finished / "export" / "joints.csv").read_bytes())
    if result.returncode == 0 and target.name != "manifest.json" and target.read_bytes() != original:
        outcome.unrecomputed += 1
        outcome.problems.append(f"{case.path} not recomputed")
    return outcome


def corruptions(finished: Path, rng: random.Random) -> list[Corruption]:
    """One seeded file of each per-frame kind, damaged both ways, plus a manifest of each kind of stage."""
    def pick(pattern: str) -> str:
        return rng.choice(sorted(path.relative_to(finished).as_posix() for path in finished.glob(pattern)))
    cases = []
    for pattern in ("silhouettes/cam*/*.png", "reconstruction/*.ply", "tracking/frames/*.json"):
        cases += [Corruption(pick(pattern), "truncate"), Corruption(pick(pattern), "flip")]
    return cases + [Corruption("reconstruction/manifest.json", "truncate"),
                    Corruption("tracking/manifest.json", "flip"), Corruption("export/joints.csv", "flip")]


def replay_concurrency(capture: Path, out: Path, joints: bytes) -> Outcome:
    """Start two runs on one output folder at once: one must finish, the other refuse in one line."""
    outcome = Outcome("concurrency", "two runs on one --out")
    command = [sys.executable, "-m", "pipeline", "run", *full_argv(capture, out)]
    processes = [subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for _ in range(2)]
    # communicate, not wait, reads the pipes while waiting: a full pipe would otherwise block the child.
    results = [subprocess.CompletedProcess(command, None, *process.communicate(timeout=TIMEOUT_S))
               for process in processes]
    for result, process in zip(results, processes, strict=True):
        result.returncode = process.returncode
    outcome.tracebacks = sum(traceback_in(result) for result in results)
    if outcome.tracebacks:
        outcome.problems.append("traceback")
    codes = sorted(result.returncode for result in results)
    if codes[0] != 0 or codes[1] == 0:
        outcome.silent_successes = int(codes == [0, 0])
        outcome.problems.append(f"exit statuses {codes} (expected one 0, one refusal)")
    for result in results:
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        if result.returncode != 0 and len(lines) != 1:
            outcome.problems.append(f"the refusal has {len(lines)} stderr lines")
    if 0 in codes and (out / "export" / "joints.csv").read_bytes() != joints:
        outcome.problems.append("joints.csv differs from a lone run's")
    return outcome


# --------------------------------------------------------------------------- the replay and its table


def replay(root: Path, seed: int, quick: bool) -> list[Outcome]:
    """Every case in a fixed order; the random delays and damaged files come from ``seed`` alone."""
    rng = random.Random(seed)
    cases = [case for case in BAD_INPUTS if not quick or case.name in QUICK_BAD_INPUTS]
    with ThreadPoolExecutor(max_workers=2) as pool:  # each case is one short process: two at a time on 2 cores
        outcomes = list(pool.map(lambda case: replay_bad_input(case, root / "bad"), cases))
    capture = fresh_capture(root / "good")
    finished = root / "good" / "finished"
    durations = []
    # The faster of two uninterrupted runs times the kills (none in a quick replay): a kill must land before
    # any run ends.
    for out in (finished,) if quick else (finished, root / "good" / "again"):
        started = time.perf_counter()
        result = pipeline_run(full_argv(capture, out))
        durations.append(time.perf_counter() - started)
        if result.returncode != 0:
            raise SystemExit(f"reliability: the uninterrupted run of the tiny sample failed: {result.stderr.strip()}")
    duration = min(durations)
    joints = (finished / "export" / "joints.csv").read_bytes()
    damages = corruptions(finished, rng)
    if quick:
        return outcomes + [replay_corruption(capture, finished, root / "corrupt-0", damages[0], rng)]
    # Kill within the run, wherever its time goes on this machine: a tenth to nine tenths of an uninterrupted one
    # (the faster of two: runs of a second or two, most of it start-up, differ by a tenth from one to the next).
    outcomes += [replay_kill(capture, root / f"kill-{index}", rng.uniform(0.1, 0.9) * duration, joints)
                 for index in range(5)]
    outcomes += [replay_corruption(capture, finished, root / f"corrupt-{index}", case, rng)
                 for index, case in enumerate(damages)]
    return outcomes + [replay_concurrency(capture, root / "concurrent", joints)]


def table(outcomes: list[Outcome]) -> str:
    """Counts per category, the numbers the issue's target is stated in."""
    header = ("category", "cases", "passed", "tracebacks", "silent successes", "user files changed",
              "unrecomputed damage")
    rows = [header]
    for category in CATEGORIES:
        mine = [outcome for outcome in outcomes if outcome.category == category]
        if mine:
            rows.append((category, len(mine), sum(o.passed for o in mine), sum(o.tracebacks for o in mine),
                         sum(o.silent_successes for o in mine), sum(o.user_files_changed for o in mine),
                         sum(o.unrecomputed for o in mine)))
    widths = [max(len(str(row[column])) for row in rows) for column in range(len(header))]
    lines = ("  ".join(str(cell).ljust(width) for cell, width in zip(row, widths, strict=True)) for row in rows)
    return "\n".join(line.rstrip() for line in lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="work folder, kept afterwards (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=13, help="seed of the kill delays and damaged files")
    parser.add_argument("--quick", action="store_true", help="3 bad inputs and 1 corruption (for the test suite)")
    args = parser.parse_args(argv)
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="reliability-") as temporary:
        root = args.out or Path(temporary)
        if root.exists() and any(root.iterdir()):
            parser.error(f"--out {root}: not empty (expected a new or empty folder)")
        outcomes = replay(root.resolve(), args.seed, args.quick)
    print(table(outcomes))
    failed = [outcome for outcome in outcomes if not outcome.passed]
    for outcome in failed:
        print(f"FAIL {outcome.category}: {outcome.name}: {'; '.join(outcome.problems)}")
    verdict = "all passed" if not failed else f"{len(failed)} of {len(outcomes)} failed"
    print(f"{verdict} ({len(outcomes)} cases, seed {args.seed}, {time.monotonic() - start:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
