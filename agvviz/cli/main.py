"""The ``agvviz`` command group: its help, and its commands in the order ``agvviz --help`` lists
them. The commands themselves are in :mod:`agvviz.cli.record_run`, :mod:`agvviz.cli.inspect`,
:mod:`agvviz.cli.viewer` and :mod:`agvviz.cli.compare`.
"""

from __future__ import annotations

import typer

from agvviz.cli import compare, inspect, record_run, viewer


class _Command(typer.core.TyperCommand):
    """A command whose ``--help`` lists on/off options as flags: typer's help would print a
    value type (``--cache/--no-cache <bool>``, ``--help <bool>``) as if they took a value."""

    def format_help(self, ctx, formatter):
        _flags_without_type(self, ctx)
        return super().format_help(ctx, formatter)


class _Group(typer.core.TyperGroup):
    """The ``agvviz`` group, its ``--help`` flag shown without a value type (see :class:`_Command`)."""

    def format_help(self, ctx, formatter):
        _flags_without_type(self, ctx)
        return super().format_help(ctx, formatter)


def _flags_without_type(command, ctx) -> None:
    for param in command.get_params(ctx):
        if getattr(param, "is_flag", False) and param.metavar is None:
            param.metavar = ""  # typer shows an option's metavar in place of its type


app = typer.Typer(
    cls=_Group,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    help="agvviz — record, replay and inspect fiducial-marker localisation in Rerun.\n\n"
    "Quick start:  agvviz demo   (records qr_floor, runs the lm solver, writes an .rrd).\n\n"
    "Exit codes: 0 ok, 1 a condition held (diff or run --fail-if) or a contract was violated (inspect), "
    "2 bad input, 3 output could not be written, 130 interrupted.",
)


# Registration order is the order of ``agvviz --help``.
app.command(cls=_Command)(record_run.scenarios)
app.command(cls=_Command)(record_run.record)
app.command(help=record_run.run_help(), cls=_Command)(record_run.run)
app.command(cls=_Command)(inspect.inspect)
app.command(cls=_Command)(viewer.view)
app.command(cls=_Command)(record_run.demo)
app.command(cls=_Command)(record_run.version)
app.command(cls=_Command)(compare.diff)
app.command(cls=_Command)(compare.sweep)
app.command(cls=_Command)(compare.budget)
app.command(cls=_Command)(compare.audit)
app.command(cls=_Command)(compare.export)
