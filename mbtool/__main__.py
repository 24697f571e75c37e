"""``python -m mbtool`` and the ``mbtool`` script (``run``, pyproject's entry point): the command
line, ``cli.main``."""

import gc


def run() -> None:
    # Start-up allocates some hundred thousand objects (click, the codec's classes) and frees
    # almost none: the cyclic collector's passes over them find nothing and cost a one-shot read
    # 8 M instructions (bench/oneshot.py).  Off while the command line is imported; main freezes
    # what start-up built and turns the collector on for the run.
    gc.disable()
    from mbtool.cli import main  # noqa: PLC0415 - imported with the collector off, above

    main()


if __name__ == "__main__":
    run()
