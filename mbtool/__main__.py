"""``python -m mbtool`` runs the same command line as the ``mbtool`` script."""

from mbtool.cli import main

main()
