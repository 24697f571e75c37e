"""The command line: the only package that imports click and rich (design notes).

``program`` is the main program (the command group, the commands' names, ``main``);
``commands/`` holds one module a family of commands; the modules beside them are what
commands share: options, settings, results, renderers, sessions.  This face names what
the rest of the world runs: ``main`` (the ``mbtool`` script, ``python -m mbtool``),
``cli`` (the group, for the docs and click's test runner) and ``COMMANDS``.
"""

from mbtool.cli.program import COMMANDS, COMPLETE_VAR, cli, main

__all__ = ["COMMANDS", "COMPLETE_VAR", "cli", "main"]
