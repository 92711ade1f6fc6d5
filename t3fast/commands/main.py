"""The ``t3fast`` command line: one sub-command per job.

Errors the user can fix (:data:`t3fast.errors.EXPECTED_ERRORS`) print one line,
``t3fast <command>: <message>``, and exit 1 (2 for bad arguments); Ctrl-C prints
``t3fast <command>: interrupted`` and exits 130 (as a shell reports SIGINT); ``--debug`` shows
the traceback too.
"""

from __future__ import annotations

import argparse
import sys
import traceback


def build_parser() -> argparse.ArgumentParser:
    from t3fast.commands.data import add_data_commands
    from t3fast.commands.demo import add_demo_command
    from t3fast.commands.evaluate import add_evaluation_commands
    from t3fast.commands.export import add_export_command
    from t3fast.commands.recipe import add_recipe_command
    from t3fast.commands.train import add_training_commands
    from t3fast.commands.view import add_view_command

    parser = argparse.ArgumentParser(prog="t3fast", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)

    info = sub.add_parser("info", help="show how the compiled operators were built")
    info.set_defaults(func=_info)

    add_demo_command(sub)
    add_data_commands(sub)
    add_training_commands(sub)
    add_recipe_command(sub)
    add_evaluation_commands(sub)
    add_export_command(sub)
    add_view_command(sub)
    _add_debug_everywhere(parser)
    return parser


def _add_debug_everywhere(parser: argparse.ArgumentParser) -> None:
    """Accept ``--debug`` after any sub-command too, and record each sub-command's name for
    error messages. SUPPRESS keeps a sub-command from resetting a ``--debug`` given before it."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                child.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                                   help="show the full traceback of an error")
                child.set_defaults(command_name=child.prog)
                _add_debug_everywhere(child)


def _info(args: argparse.Namespace) -> int:
    import t3fast

    for key, value in t3fast.build_info().items():
        print(f"{key}: {value}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from t3fast.errors import EXPECTED_ERRORS, UsageError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except EXPECTED_ERRORS as exc:
        if args.debug:
            traceback.print_exc()
        message = str(exc) or type(exc).__name__
        print(f"{args.command_name}: {message}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    except KeyboardInterrupt:  # outside the training loop, which stops cleanly on its own
        if args.debug:
            traceback.print_exc()
        print(f"{args.command_name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
