"""The ``t3fast`` command line: one sub-command per job."""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    from t3fast.data.commands import add_data_commands
    from t3fast.demo import add_demo_command
    from t3fast.evaluation.commands import add_evaluation_commands
    from t3fast.training.commands import add_training_commands

    parser = argparse.ArgumentParser(prog="t3fast", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    info = sub.add_parser("info", help="show how the compiled operators were built")
    info.set_defaults(func=_info)

    add_demo_command(sub)
    add_data_commands(sub)
    add_training_commands(sub)
    add_evaluation_commands(sub)
    return parser


def _info(args: argparse.Namespace) -> int:
    import t3fast

    for key, value in t3fast.build_info().items():
        print(f"{key}: {value}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
