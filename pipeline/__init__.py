"""Orchestration: reads captures, runs the stage graph with a disk cache, owns every file written.

Entry point ``python -m pipeline`` (:mod:`pipeline.cli`); the stage graph is :mod:`pipeline.graph`,
the cache and resume rules :mod:`pipeline.engine.runner`, the capture reader :mod:`pipeline.io.capture`.
"""
