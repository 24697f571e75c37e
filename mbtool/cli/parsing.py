"""How mbtool's commands parse their command line where click's way costs or confuses: --help
without gettext, negative numbers as arguments, and a close match for a mistyped name."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click


def _is_number(token: str) -> bool:
    try:
        float(token) if not token.lower().lstrip("+-").startswith("0x") else int(token, 16)
    except ValueError:
        return False
    return True


def _show_help(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value and not ctx.resilient_parsing:
        click.echo(ctx.get_help(), color=ctx.color)
        ctx.exit()


def did_you_mean(close: list[str]) -> str:
    """ "; did you mean a, b or c?" for the close matches of a mistyped name, best first."""
    if not close:
        return ""
    words = close[0] if len(close) == 1 else f"{', '.join(close[:-1])} or {close[-1]}"
    return f"; did you mean {words}?"


if TYPE_CHECKING:
    _Command = click.Command  # what QuickHelp is mixed into
else:
    _Command = object


class QuickHelp(_Command):
    """A --help option made without click's gettext look-up, which imports locale on every run."""

    def get_help_option(self, ctx: click.Context) -> click.Option | None:
        names = self.get_help_option_names(ctx)
        if not names or not self.add_help_option:
            return None
        return click.Option(
            names,
            is_flag=True,
            is_eager=True,
            expose_value=False,
            callback=_show_help,
            help="Show this message and exit.",
        )


class DeviceCommand(QuickHelp, click.Command):
    """Takes negative numbers as arguments (write-register 100 -5) yet still refuses unknown options."""

    def parse_args(self, ctx, args):
        params = self.get_params(ctx)
        known = {name for param in params for name in param.opts + param.secondary_opts}
        # Click tries every short option as a long one first, and the internal
        # "no such option" it raises imports difflib and gettext: ~2 ms a run that
        # a cron job pays.  Naming the long option up front skips that detour.
        longer = {
            short: max(param.opts, key=len)
            for param in params
            for short in param.opts
            if len(short) == 2 and short[0] == "-" and short[1] != "-"
        }
        args = list(args)
        for i, token in enumerate(args):
            if token == "--":
                break
            if token in longer:
                args[i] = longer[token]
            elif token.startswith("-") and len(token) > 1 and not _is_number(token):
                name = token.split("=", 1)[0]
                if name not in known and not (name[:2] in known and not name.startswith("--")):
                    import difflib  # noqa: PLC0415 - 0.8 ms: a mistyped option only

                    close = difflib.get_close_matches(name, sorted(known), n=3, cutoff=0.6)
                    raise click.UsageError(f"no such option {name}{did_you_mean(close)}", ctx)
        return super().parse_args(ctx, args)
