"""The command line's commands, one module each; :mod:`paradrive.cli` gathers them.

Each module holds one command's options, help and output and exposes ``register(app)``; the
work is done by the library modules it calls, which return data, plain strings or typed records
and print nothing. Only this package and :mod:`paradrive.cli` import typer or rich. A command
imports what it drives when it runs, so ``paradrive --help`` and ``paradrive status`` start
without torch. :mod:`paradrive.commands.common` holds what they share: the consoles, the
one-line error and the defaults of the common options.
"""
