"""Subcommands of ``jaxinertia`` provided by this package."""

from __future__ import annotations

__all__ = ["register"]


def register(sub) -> None:
    """Adds this package's subcommands to the ``jaxinertia`` argparse subparsers."""
