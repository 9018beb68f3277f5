"""``evseg evaluate``: the paper's evaluation protocols, one module each."""

from __future__ import annotations

import argparse

from evseg_torch.app.cli import evaluate_eed, evaluate_evimo, evaluate_labelled, evaluate_synthetic


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add ``evaluate`` and its protocols to ``commands`` (a subparsers action)."""
    evaluate = commands.add_parser(
        "evaluate",
        parents=[common],
        help="evaluate against ground truth",
        description="Evaluation protocols of the paper.",
    )
    protocols = evaluate.add_subparsers(title="protocols", required=True, metavar="PROTOCOL")
    for protocol in (evaluate_synthetic, evaluate_eed, evaluate_evimo, evaluate_labelled):
        protocol.add_parser(protocols, common)
