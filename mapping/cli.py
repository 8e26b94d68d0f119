"""``skyfix lens``, ``skyfix plan`` and ``skyfix map``: the mapping commands, one module each
(:mod:`~skyfix.mapping.lens_cli`, :mod:`~skyfix.mapping.plan_cli`, :mod:`~skyfix.mapping.map_cli`).
"""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lens``, ``plan`` and ``map`` to the ``skyfix`` command line."""
    from skyfix.mapping.lens_cli import register_lens
    from skyfix.mapping.map_cli import register_map
    from skyfix.mapping.plan_cli import register_plan

    register_lens(subparsers)
    register_plan(subparsers)
    register_map(subparsers)
