"""Stage runner with a disk cache: run what is out of date, skip the rest, resume interrupted work.

A stage is a declaration (:class:`~pipeline.engine.stage.Stage`): a name, the upstream stages it reads, its
parameter dataclass, the parts of the capture it reads, and a run function. Each stage writes only under
``<out>/<stage>/``. When it finishes, the runner writes ``<out>/<stage>/manifest.json``::

    stage, cache_key, code_version, package_version, params, inputs, outputs, timing, finished_at

The **cache key** (:mod:`pipeline.engine.cache`) is the hash of: stage name, code version, the canonical
JSON of the stage's own parameters (only its section, so a tracker parameter does not invalidate
silhouettes), and its input hashes: each upstream stage's output digest (content hash of its files, so an
upstream rerun that produces identical files does not ripple down) and a fingerprint of each capture part
it reads (content for capture.yaml and the calibration, path + size + mtime for media files). The code
version is the package version plus a hash of the code and data the stage runs and reads
(:func:`~pipeline.engine.versions.code_inputs`): the run function with the helpers and constants of its
module it uses, and every file of the modules and packages listed in ``Stage.code`` (data files such as
the tracker's pose library included).

A stage is **up to date** when its manifest parses, its key equals the one computed now, and its
output files are still the ones it wrote: the manifest records each file's content hash, and the
check hashes them all again (cheap: :func:`~pipeline.engine.cache.output_contents`), so a damaged file is
noticed whatever its format. A corrupt manifest is a logged miss.

**Interruptions.** The manifest is written last, so a stage folder without one is incomplete.
Before any work, the runner deletes the old manifest and writes a ``params_hash`` marker holding
the key; per-frame outputs are written atomically (temp file + ``os.replace``), so an existing
frame file is a finished frame once it passes the content check its format carries
(:func:`pipeline.io.frames_io.file_problem`). On the next run, if the marker holds the same key, the
folder is kept and the stage only computes the frames whose files are missing or damaged (files that
differ from an old manifest's hashes are deleted first); otherwise the folder is emptied first. A
streaming stage running alongside its upstream (the tracking beside the reconstruction) cannot know its
key yet, since that names the upstream's output digest: its marker holds
:func:`~pipeline.engine.cache.streamed_key`, made with the upstream's cache key instead, and a run that
finds it resumes there too. So a run never trusts a stale, damaged or half-written result; and a damaged
file a stage still comes to read (:class:`~pipeline.io.frames_io.DamagedFileError`) is deleted and
computed again (:meth:`Runner.run`).

**What the runner deletes** (:mod:`pipeline.engine.output_folder`). Only what it can show it wrote: a
stage folder is emptied only when it holds the marker (written as the folder is made, before any result),
and an output folder may not overlap the capture (be it, lie inside it or contain it), so that ``--out``
pointed at the capture cannot empty the capture's own ``calibration/`` or ``silhouettes/``. Anything else
in the way is an :class:`InputError` naming it.

A lock (``fcntl.flock`` on ``<out>/.lock``) refuses a second concurrent run on the same folder.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import shutil
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from calib.errors import InputError
from pipeline.engine import run_warnings
from pipeline.engine.cache import (
    Expected,
    describe_outputs,
    expected_record,
    listing,
    output_changes,
    read_manifest,
    streamed_key,
    unrecorded_files,
)
from pipeline.engine.context import StageContext
from pipeline.engine.executors import Workers
from pipeline.engine.output_folder import check_output_folder, fresh_stage_folder, write_run_record, written_by_runner
from pipeline.engine.stage import Stage, check_graph
from pipeline.engine.status import stage_status, stale_reasons
from pipeline.engine.versions import package_version
from pipeline.io import atomic, frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import MANIFEST, MARKER, RUN_RECORD

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StageOutcome:
    """What happened to one stage in a run: ``action`` is "ran", "up to date" or "not selected"."""

    name: str
    action: str
    seconds: float = 0.0
    frames: int | None = None
    reason: str = ""


@dataclass
class Runner:
    """Runs a stage graph on one capture into one output folder (hold
    :func:`~pipeline.engine.output_folder.output_lock` around it)."""

    stages: Sequence[Stage]
    capture: Capture
    params: Mapping[str, Any]
    output_root: Path
    workers: Workers
    show_progress: bool = False
    record_facts: Mapping[str, Any] = field(default_factory=dict)
    outcomes: list[StageOutcome] = field(default_factory=list)
    _changing: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        check_graph(self.stages)
        check_output_folder(self.output_root, self.capture.root)

    def run(self, selected: Collection[str] | None = None, *, force: bool = False) -> list[StageOutcome]:
        """Run the ``selected`` stages (default all) in declaration order; return what happened.

        A streaming stage that has no finished result yet runs alongside its upstream when that one
        has work to do: the upstream in a background thread (its workers compute the frames), the
        streaming stage here, reading each frame as it appears. The tracker, sequential by nature,
        then uses the core the per-frame stage's workers leave idle between chunks.

        A stage that reads a damaged output of a stage (:class:`~pipeline.io.frames_io.DamagedFileError`)
        does not end the run: the file is deleted, its stage loses its manifest, and the run starts
        again with that stage selected too, which computes the file again as it resumes (each file is
        repaired once; a second failure is raised).

        A run that fails after it began to change the folder leaves nothing that looks finished: a stage it
        left incomplete keeps the frames it wrote, without a manifest, so that the next run resumes from
        them; a finished stage downstream of one is removed (:meth:`_invalidate`), its results having been
        made from files the failed run replaced; ``run.json`` records the failure and names the stages left
        incomplete.
        """
        selected = set(selected) if selected is not None else {stage.name for stage in self.stages}
        forced = set(selected) if force else set()
        ran: dict[str, StageOutcome] = {}
        repaired: set[Path] = set()
        self._changing = False
        try:
            while True:
                try:
                    self._run_once(selected, forced)
                    break
                except frames_io.DamagedFileError as error:
                    selected.add(self._repair(error, repaired))
                    ran.update({outcome.name: outcome for outcome in self.outcomes if outcome.action == "ran"})
                    forced -= set(ran)
        except BaseException as error:  # Ctrl-C too: what the run left must not look finished
            if self._changing:
                self._record_failure(error)
            raise
        if self._changing:
            write_run_record(self.output_root, self.capture, self.params, "finished", facts=self.record_facts)
        self.outcomes = [ran.get(outcome.name, outcome) if outcome.action == "up to date" else outcome
                         for outcome in self.outcomes]
        return self.outcomes

    def _begin_change(self) -> None:
        """Called before the run first changes a stage folder: ``run.json`` says it is for this run now."""
        if not self._changing:
            write_run_record(self.output_root, self.capture, self.params, "running", facts=self.record_facts)
            self._changing = True

    def _record_failure(self, error: BaseException) -> None:
        """Mark what a failed run left incomplete (:meth:`_invalidate`), in ``run.json`` and the debug log: the
        run's own one-line error is what the terminal shows, ``pipeline stages`` reports the rest."""
        incomplete = self._invalidate()
        if isinstance(error, KeyboardInterrupt):
            message = "interrupted (Ctrl-C)"
        else:
            message = str(error).splitlines()[0] if str(error).strip() else type(error).__name__
        log.debug("the run failed; %s left incomplete (no manifest; their files are kept and the next run "
                    "resumes from them; `python -m pipeline stages %s` lists them)",
                    ", ".join(incomplete) or "no stage", self.output_root)
        try:
            write_run_record(self.output_root, self.capture, self.params, "failed", facts=self.record_facts,
                             failure={"error": message, "incomplete": incomplete})
        except OSError as failure:  # a full disk, say: the run's own error is the one to show
            log.warning("%s: could not record the failure (%s)", self.output_root / RUN_RECORD, failure)

    def _invalidate(self) -> list[str]:
        """Remove every finished stage folder one of whose upstreams is unfinished; return the stages of the
        folder that are incomplete (a marker, no manifest), in order.

        Such a stage's results were made from files the failed run replaced or left unfinished: kept without
        their manifest, they would still look like this capture's results to whoever opens them (a report,
        a joints.csv that ``pipeline eval`` scores), and the next run, whose inputs differ, could not resume
        from them anyway. A folder holding a file its manifest does not list (a user's) is left as it is: the run
        that must redo the stage names that file (`fresh_stage_folder`).
        """
        complete: dict[str, bool] = {}
        incomplete = []
        for stage in self.stages:
            folder = self.output_root / stage.name
            has_manifest = (folder / MANIFEST).is_file()
            if has_manifest and not all(complete.get(name, False) for name in stage.inputs):
                if unrecorded_files(folder):  # a user's file: the next run refuses to delete it, and says so
                    continue
                with contextlib.suppress(OSError):  # the run's own error is the one to show
                    if written_by_runner(folder):
                        shutil.rmtree(folder)
                (folder / MANIFEST).unlink(missing_ok=True)
                has_manifest = False
            complete[stage.name] = has_manifest
            if not has_manifest and written_by_runner(folder):
                incomplete.append(stage.name)
        return incomplete

    def _run_once(self, selected: Collection[str], forced: Collection[str]) -> None:
        """One pass of :meth:`run` over the stages, the ``forced`` ones rerun even if up to date."""
        self.outcomes = []
        stages = list(self.stages)
        while stages:
            stage = stages.pop(0)
            if stage.name not in selected:
                self.outcomes.append(StageOutcome(stage.name, "not selected"))
            elif stages and stages[0].name in selected and self._streams_after(stage, stages[0], forced):
                self.outcomes.extend(self._run_streaming(stage, stages.pop(0), forced))
            else:
                self.outcomes.append(self.run_stage(stage, force=stage.name in forced))

    def _repair(self, error: frames_io.DamagedFileError, repaired: set[Path]) -> str:
        """Delete the damaged file of ``error`` and its stage's manifest; return that stage's name.

        Raises ``error`` again when the file is not in a stage folder the runner wrote (a capture's
        file is the user's to replace) or was repaired before in this run.
        """
        path = error.path.resolve()
        owner = next((stage.name for stage in self.stages
                      if (self.output_root / stage.name).resolve() in path.parents), None)
        if owner is None or not written_by_runner(self.output_root / owner) or path in repaired:
            raise error
        self._begin_change()
        repaired.add(path)
        log.warning("%s: %s; deleted, the %s stage computes it again", error.path, error.problem, owner)
        path.unlink(missing_ok=True)
        (self.output_root / owner / MANIFEST).unlink(missing_ok=True)
        return owner

    def _streams_after(self, upstream: Stage, stage: Stage, forced: Collection[str]) -> bool:
        """Whether ``stage`` should run alongside ``upstream``: it streams from it, will run anyway (no
        finished result of its own), and ``upstream`` has work to do."""
        if not stage.streams or stage.inputs[-1:] != (upstream.name,):
            return False
        if read_manifest(self.output_root / stage.name) is not None and stage.name not in forced:
            return False  # it may still be up to date after the upstream reruns: wait and see
        status = stage_status(upstream, self.capture, self.params[upstream.name], self.output_root)
        return upstream.name in forced or status.state != "up to date"

    def _run_streaming(self, upstream: Stage, stage: Stage, forced: Collection[str]) -> list[StageOutcome]:
        upstream_key = expected_record(upstream, self.capture, self.params[upstream.name], self.output_root).key
        key = streamed_key(stage, self.capture, self.params[stage.name], self.output_root, upstream_key)
        prepared = self._prepare(upstream, force=upstream.name in forced)  # before the follower looks at its folder
        with cf.ThreadPoolExecutor(1, thread_name_prefix=upstream.name) as background:
            if isinstance(prepared, StageOutcome):
                running = cf.Future()
                running.set_result(prepared)
            else:
                running = background.submit(self._run_prepared, upstream, prepared)
            outcome = self._run_streaming_stage(stage, running, key, force=stage.name in forced)
        return [running.result(), outcome]

    def run_stage(self, stage: Stage, *, force: bool = False) -> StageOutcome:
        """Run one stage unless up to date, resuming from the frames an interrupted run left when its
        marker holds the key computed now (or, for a streaming stage, the key it ran under alongside
        its upstream, :func:`~pipeline.engine.cache.streamed_key`, when that upstream has finished since)."""
        prepared = self._prepare(stage, force=force)
        return prepared if isinstance(prepared, StageOutcome) else self._run_prepared(stage, prepared)

    def _prepare(self, stage: Stage, *, force: bool) -> StageOutcome | Expected:
        """The outcome of a stage that is up to date; else its folder made ready to run in (resumed or
        emptied) and the record it is to run under.

        A streaming follower starts only after this, so it never reads the files of an earlier run
        that its upstream is about to delete."""
        folder = self.output_root / stage.name
        expected = expected_record(stage, self.capture, self.params[stage.name], self.output_root)
        if expected.missing:
            upstream = expected.missing[0]
            raise InputError(f"{self.output_root / upstream}: stage {stage.name} needs the results of "
                             f"{upstream}, which are not complete (expected a finished {upstream} stage; "
                             "run it first)")
        manifest = read_manifest(folder)
        changes = None
        if manifest is not None and not force:
            reasons = stale_reasons(manifest, expected)
            changes = None if reasons else output_changes(folder, manifest)
            if not reasons and not changes:
                log.info("%s: up to date", stage.name)
                return StageOutcome(stage.name, "up to date", reason="")
            log.info("%s: stale (%s)", stage.name, "; ".join(reasons) or str(changes))
        self._begin_change()
        if changes and changes.changed:  # deleted, so that the resume below computes them again
            log.warning("%s: %d files differ from what the stage wrote (%s); deleted, computed again",
                        stage.name, len(changes.changed), listing(changes.changed))
            for name in changes.changed:
                (folder / name).unlink()

        self._resume_or_start_afresh(stage, (expected.key, *self._streamed_keys(stage)), expected.key, force)
        return expected

    def _run_prepared(self, stage: Stage, expected: Expected) -> StageOutcome:
        """Run a stage whose folder :meth:`_prepare` made ready, and record it under ``expected``."""
        frames, seconds = self._execute(stage)
        return self._finish(stage, expected, frames, seconds)

    def _streamed_keys(self, stage: Stage) -> tuple[str, ...]:
        """The key a streaming ``stage`` ran under alongside its finished upstream
        (:func:`~pipeline.engine.cache.streamed_key`)."""
        manifest = read_manifest(self.output_root / stage.inputs[-1]) if stage.streams else None
        if manifest is None:
            return ()
        return (streamed_key(stage, self.capture, self.params[stage.name], self.output_root, manifest["cache_key"]),)

    def _resume_or_start_afresh(self, stage: Stage, resumable_keys: Sequence[str], key: str, force: bool) -> None:
        """Keep the stage folder's finished frames when its marker holds one of ``resumable_keys`` (and the
        run is not forced); else empty it, with a marker holding ``key``."""
        folder = self.output_root / stage.name
        if not force and written_by_runner(folder) and (
                folder / MARKER).read_text(encoding="utf-8").strip() in resumable_keys:
            (folder / MANIFEST).unlink(missing_ok=True)
            removed = atomic.remove_temp_files(folder)
            log.info("%s: resuming (%d leftover temporary files removed)", stage.name, removed)
        else:
            fresh_stage_folder(folder, key)

    def _run_streaming_stage(self, stage: Stage, upstream: cf.Future, key: str, *, force: bool) -> StageOutcome:
        """Run ``stage`` alongside ``upstream``, the future of its running input stage: under ``key`` (its
        :func:`~pipeline.engine.cache.streamed_key`), resuming what a run under the same key left; its record
        is made when both have finished."""
        folder = self.output_root / stage.name
        self._begin_change()
        self._resume_or_start_afresh(stage, (key,), key, force)
        frames, seconds = self._execute(stage, upstream)
        upstream.result()  # its manifest is written: this stage's inputs are known now
        expected = expected_record(stage, self.capture, self.params[stage.name], self.output_root)
        atomic.write_text(folder / MARKER, expected.key + "\n")
        return self._finish(stage, expected, frames, seconds)

    def _execute(self, stage: Stage, upstream: cf.Future | None = None) -> tuple[int | None, float]:
        """Call the stage's run function in its folder: the frames it computed and the seconds it took."""
        context = StageContext(stage.name, self.capture, self.params[stage.name], self.output_root / stage.name,
                               self.output_root, self.workers, self.show_progress, upstream)
        started = time.perf_counter()
        try:
            with run_warnings.stage_scope(stage.name):
                frames = stage.run(context)
        finally:  # what the stage logged is shown before what comes after it (`terminal.FoldingStreamHandler`)
            for handler in logging.getLogger().handlers:
                with contextlib.suppress(OSError, ValueError):  # a stream closed under it, as logging.shutdown allows
                    handler.flush()
        return frames, time.perf_counter() - started

    def _finish(self, stage: Stage, expected: Expected, frames: int | None, seconds: float) -> StageOutcome:
        """Write the manifest of a stage that ran: from now on it is up to date."""
        folder = self.output_root / stage.name
        manifest = {
            **expected.record,
            "cache_key": expected.key,
            "package_version": package_version(),
            "outputs": describe_outputs(folder),
            "timing": {"seconds": round(seconds, 6), "frames": frames, "workers": self.workers.description},
            "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        frames_io.write_json(folder / MANIFEST, manifest)
        return StageOutcome(stage.name, "ran", seconds, frames)


def format_summary(outcomes: Sequence[StageOutcome]) -> str:
    """Table of what each stage did, with its time per frame and frames per second."""
    rows = [("stage", "action", "seconds", "frames", "ms/frame", "frames/s")]
    for outcome in outcomes:
        timed = outcome.action == "ran"
        per_frame = timed and outcome.frames
        rows.append((
            outcome.name, outcome.action,
            f"{outcome.seconds:.2f}" if timed else "-",
            str(outcome.frames) if timed and outcome.frames is not None else "-",
            f"{1000 * outcome.seconds / outcome.frames:.1f}" if per_frame else "-",
            f"{outcome.frames / outcome.seconds:.2f}" if per_frame and outcome.seconds > 0 else "-",
        ))
    return format_columns(rows, right=range(2, len(rows[0])))


def format_columns(rows: Sequence[Sequence[str]], *, right: Collection[int]) -> str:
    """Rows of text cells as aligned columns: those numbered in ``right`` (numbers) to the right, the others
    (names, words) to the left."""
    widths = [max(len(row[column]) for row in rows) for column in range(len(rows[0]))]
    return "\n".join("  ".join(cell.rjust(width) if column in right else cell.ljust(width)
                               for column, (cell, width) in enumerate(zip(row, widths, strict=True))).rstrip()
                     for row in rows)

