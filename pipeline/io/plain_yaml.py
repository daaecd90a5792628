"""YAML as users write it for the pipeline: plain values, no aliases.

An alias (``*name``) stands for a node anchored earlier (``&name``); nested, a few hundred bytes of
them stand for gigabytes once anything walks the data (a "billion laughs"). ``capture.yaml``,
``--config`` files and ``--set`` values never need them, so :func:`load` refuses the first alias it meets,
before anything is built.
"""

from __future__ import annotations

from typing import Any

import yaml

from calib.errors import InputError


class _NoAliasLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that stops at the first alias, naming its line."""

    def __init__(self, stream: str, source: str) -> None:
        super().__init__(stream)
        self.source = source

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise InputError(f"{self.source}: line {event.start_mark.line + 1}: alias *{event.anchor} "
                             "(expected plain values without YAML aliases, which can make a small file huge)")
        return super().compose_node(parent, index)


def load(text: str, source: str) -> Any:
    """The plain data of the YAML ``text``; ``source`` (a path, ``--set``) names it in errors.

    Raises
    ------
    InputError
        At an alias.
    yaml.YAMLError
        When ``text`` is not YAML (the caller says what it expected).
    """
    loader = _NoAliasLoader(text, source)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def describe_error(error: yaml.YAMLError | UnicodeDecodeError) -> str:
    """One line for a YAML (or text decoding) error: what is wrong and where, ``line L, column C`` of the text,
    so that a user finds the typo without a traceback (the error's own text spreads over several lines)."""
    problem = getattr(error, "problem", None) or getattr(error, "context", None)
    mark = getattr(error, "problem_mark", None) or getattr(error, "context_mark", None)
    if problem and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
