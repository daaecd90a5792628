"""What a stage's run function sees (:class:`StageContext`): its capture, parameters and folders, and
:meth:`~StageContext.map_frames`, which hands chunks of pending frames to the workers; a frame whose files
exist and pass their content check is done, which is how an interrupted run resumes."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from calib.errors import InputError
from pipeline.engine.executors import Workers, call_logged, relog
from pipeline.io import frames_io
from pipeline.io.capture import Capture

log = logging.getLogger(__name__)

#: Largest chunk of consecutive frames given to one worker call. Bigger chunks decode video with
#: fewer seeks; smaller ones balance load and update the progress bar more often.
MAX_CHUNK_FRAMES = 25
#: Chunks per worker to aim for, so that an uneven chunk does not leave workers idle at the end.
CHUNKS_PER_WORKER = 4


@dataclass(frozen=True)
class StageContext:
    """Everything a stage's run function may use. Stages write only under ``out_dir``."""

    stage: str
    capture: Capture
    params: Any
    out_dir: Path
    output_root: Path
    workers: Workers
    show_progress: bool = False
    upstream: cf.Future | None = None

    def input_dir(self, stage: str) -> Path:
        """Folder of an upstream stage's results."""
        return self.output_root / stage

    def ready(self, path: Path) -> Path:
        """``path``, an input file, once it exists.

        While a streaming stage's upstream is still running (``upstream``, the future of its
        :meth:`~pipeline.engine.runner.Runner.run_stage`), files appear one by one, each complete (they are written
        atomically); waiting ends with the file, or with the upstream's own error if it failed.
        """
        while not path.exists():
            if self.upstream is None or self.upstream.done():
                if path.exists():
                    break
                if self.upstream is not None:
                    self.upstream.result()  # the upstream's error, if it failed
                raise InputError(f"{path}: input file missing (expected the {self.stage} stage's inputs complete)")
            time.sleep(STREAM_POLL_S)
        return path

    def progress(self, total: int, *, initial: int = 0) -> tqdm:
        """A progress bar over frames on stderr (disabled when not wanted or not a terminal)."""
        return tqdm(total=total, initial=initial, desc=self.stage, unit="frame", file=sys.stderr,
                    disable=not self.show_progress, leave=False, dynamic_ncols=True)

    def pending_frames(self, outputs_of: Callable[[int], Sequence[Path]],
                       frames: Sequence[int] | None = None) -> list[int]:
        """Frames (default: all of the capture's) for which some output file is missing or damaged.

        A file kept from an interrupted run counts only when it passes its content check
        (:func:`~pipeline.io.frames_io.file_problem`); one that fails is deleted here, with a warning, so
        that its frame is computed again and nothing reads the damaged file meanwhile.
        """
        frames = self.capture.frame_numbers if frames is None else frames
        return [frame for frame in frames if not all(_intact(path) for path in outputs_of(frame))]

    def map_frames(self, task: Callable[[tuple[int, ...]], Any],
                   outputs_of: Callable[[int], Sequence[Path]], *,
                   frames: Sequence[int] | None = None, chunk_size: int | None = None) -> int:
        """Run ``task(chunk)`` over chunks of consecutive pending frames with the executor.

        ``task`` runs in a worker (another process, or another machine with Dask): it must be
        picklable, e.g. ``functools.partial(module_level_function, capture=..., params=...,
        out_dir=...)``, and it **writes each frame's outputs itself**, atomically (``frames_io``
        writers), so that a frame's files exist only once complete and nothing large travels back
        to this process. Its return value is ignored. ``outputs_of(frame)`` lists the files that
        make a frame complete; frames whose files all exist are skipped (this is resuming).

        Returns
        -------
        int
            Number of frames computed now.
        """
        frames = self.capture.frame_numbers if frames is None else tuple(frames)
        pending = self.pending_frames(outputs_of, frames)
        if not pending:
            return 0
        size = chunk_size or min(MAX_CHUNK_FRAMES,
                                 max(1, math.ceil(len(pending) / (CHUNKS_PER_WORKER * self.workers.count))))
        chunks = consecutive_chunks(pending, frames, size)
        executor = self.workers.executor
        # Submitting a few chunks ahead keeps every worker busy without queueing the whole sequence;
        # with one in-process worker it means "one chunk at a time", so a failure stops at once.
        ahead = 1 if self.workers.count == 1 else 2 * self.workers.count
        remaining = iter(chunks)
        running: dict[cf.Future, tuple[int, ...]] = {}
        with self.progress(len(frames), initial=len(frames) - len(pending)) as bar:
            try:
                while True:
                    while len(running) < ahead and (chunk := next(remaining, None)) is not None:
                        future = executor.submit(task, chunk) if self.workers.in_process else \
                            executor.submit(call_logged, task, chunk)  # the worker's warnings come back
                        running[future] = chunk
                    if not running:
                        break
                    done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                    for future in done:
                        chunk = running.pop(future)
                        result = future.result()
                        if not self.workers.in_process:
                            relog(result)
                        bar.update(len(chunk))
            finally:
                for future in running:
                    future.cancel()
        return len(pending)


def _intact(path: Path) -> bool:
    """Whether the output file ``path`` exists and passes its content check (else it is deleted)."""
    if not path.exists():
        return False
    problem = frames_io.file_problem(path)
    if problem:
        log.warning("%s: %s; deleted, computed again", path, problem)
        path.unlink()
    return problem is None


#: How often a streaming stage looks for its next input file, seconds.
STREAM_POLL_S = 0.002


def consecutive_chunks(pending: Sequence[int], frames: Sequence[int], size: int) -> list[tuple[int, ...]]:
    """Split ``pending`` into chunks of at most ``size`` frames that are consecutive in ``frames``.

    Consecutive (in the capture's frame order) so that a worker decodes a video sequentially.
    """
    position = {frame: index for index, frame in enumerate(frames)}
    chunks: list[list[int]] = []
    for frame in pending:
        if chunks and len(chunks[-1]) < size and position[frame] == position[chunks[-1][-1]] + 1:
            chunks[-1].append(frame)
        else:
            chunks.append([frame])
    return [tuple(chunk) for chunk in chunks]
