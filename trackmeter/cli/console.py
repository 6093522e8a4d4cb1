"""trackmeter console (not built yet)."""

from __future__ import annotations

import argparse

from trackmeter.cli.common import not_built_yet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    return not_built_yet("console")
