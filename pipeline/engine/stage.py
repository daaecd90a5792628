"""Stage declarations: what a stage is (:class:`Stage`), a graph's checks, and the ``--only/--from/--to``
selection."""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from calib.errors import InputError
from pipeline.engine.context import StageContext

_STAGE_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline graph.

    Parameters
    ----------
    name : str
        Folder name under the output directory and section name in the configuration.
    run : callable
        ``run(ctx: StageContext) -> int | None``: does the work, writes files under ``ctx.out_dir``,
        returns the number of frames it computed (``None`` if the stage is not per-frame).
    inputs : tuple of str
        Upstream stages whose results it reads (through ``ctx.input_dir(name)``).
    params_type : type or None
        Frozen dataclass of its parameters (every field with a default), or ``None``. Its method
        ``input_files()``, if it has one, names the files outside the capture that the parameters point
        to (a body file); their contents are part of the stage's key (:func:`~pipeline.engine.cache.file_digest`).
    capture_parts : tuple of str
        Parts of the capture it reads directly (see :meth:`~pipeline.io.capture.Capture.fingerprint`).
    code : tuple of str
        Modules, packages or resource folders (import names) whose files are part of its code version,
        in addition to the run function and the helpers of its module it uses, e.g.
        ``("stages.silhouettes",)``: every first-party module whose code the stage runs and every data
        file it reads, which tests/pipeline/test_graph.py checks (see :func:`~pipeline.engine.versions.code_inputs`).
    streams : bool
        The stage may run while its last input stage is still writing: it reads each input file
        through :meth:`~pipeline.engine.context.StageContext.ready`, which waits for the file. A run then
        overlaps the two (see :meth:`~pipeline.engine.runner.Runner.run`).
    """

    name: str
    run: Callable[[StageContext], int | None]
    inputs: tuple[str, ...] = ()
    params_type: type | None = None
    capture_parts: tuple[str, ...] = ()
    code: tuple[str, ...] = ()
    streams: bool = False

    def __post_init__(self) -> None:
        if not _STAGE_NAME.match(self.name):
            raise ValueError(f"stage name {self.name!r}: expected lower_case letters, digits and _")


def check_graph(stages: Sequence[Stage]) -> None:
    """Raise ``ValueError`` unless names are unique and every input is declared before its user."""
    seen: set[str] = set()
    for stage in stages:
        if stage.name in seen:
            raise ValueError(f"stage {stage.name!r} is declared twice")
        unknown = [name for name in stage.inputs if name not in seen]
        if unknown:
            raise ValueError(f"stage {stage.name!r} reads {unknown}, which are not declared before it")
        seen.add(stage.name)


def select_stages(stages: Sequence[Stage], *, only: str | None = None, start: str | None = None,
                  end: str | None = None) -> list[str]:
    """Names of the stages to run for ``--only``, ``--from`` and ``--to`` (all when none is given).

    ``--from S`` selects S and every stage downstream of it; ``--to S`` selects S and every stage
    upstream of it; both together select the stages in between.
    """
    names = [stage.name for stage in stages]
    for option, value in (("--only", only), ("--from", start), ("--to", end)):
        if value is not None and value not in names:
            raise InputError(f"{option} {value}: unknown stage (expected one of {', '.join(names)})")
    if only is not None:
        return [only]
    by_name = {stage.name: stage for stage in stages}
    selected = set(names)
    if start is not None:
        downstream = {start}
        for stage in stages:
            if downstream.intersection(stage.inputs):
                downstream.add(stage.name)
        selected &= downstream
    if end is not None:
        upstream, todo = set(), [end]
        while todo:
            name = todo.pop()
            if name not in upstream:
                upstream.add(name)
                todo.extend(by_name[name].inputs)
        selected &= upstream
    if not selected:
        raise InputError(f"--from {start} --to {end}: no stage lies between them "
                         "(expected --from upstream of --to)")
    return [name for name in names if name in selected]

