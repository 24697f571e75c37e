"""Shell completion of -p (the URL schemes, the serial devices there are) and -P (profiles)."""

from __future__ import annotations

import click

# Where serial adapters appear (Linux, macOS); completion offers the ones present.
SERIAL_DEVICE_GLOBS = (
    "/dev/ttyUSB*",
    "/dev/ttyACM*",
    "/dev/ttyAMA*",
    "/dev/ttyS*",
    "/dev/tty.usb*",
    "/dev/serial/by-id/*",
)


def complete_port(ctx: click.Context, param: click.Parameter, incomplete: str) -> list:
    """-p TAB: the URL schemes, the serial devices there are, and file names for other paths."""
    import glob  # noqa: PLC0415 - TAB only: every command loads this module

    from click.shell_completion import CompletionItem  # noqa: PLC0415 - TAB only, 0.5 ms

    from mbtool.link.transport import schemes  # noqa: PLC0415 - TAB only: 5 M instructions

    offers = [f"{scheme}://" for scheme in schemes()]
    offers += sorted(path for pattern in SERIAL_DEVICE_GLOBS for path in glob.glob(pattern))
    found = [CompletionItem(offer) for offer in offers if offer.startswith(incomplete)]
    if not found and "://" not in incomplete:
        return [CompletionItem(incomplete, type="file")]  # a device path typed by hand
    return found


def complete_profile(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[str]:
    from mbtool.cli.profiles import names  # noqa: PLC0415 - TAB only

    return [name for name in names() if name.startswith(incomplete)]
