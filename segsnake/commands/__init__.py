"""Sub-commands of the ``segsnake`` CLI; each module has ``add_parser`` and sets ``func``."""

import argparse


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


def add_wait_option(parser: argparse.ArgumentParser) -> None:
    """``--wait``: the commands whose output directory is locked (:mod:`segsnake.outdir`)."""
    parser.add_argument("--wait", action="store_true",
                        help="when another segsnake run is writing into --out, wait for it "
                             "instead of refusing (exit 5)")
