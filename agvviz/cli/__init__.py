"""agvviz command line: parse, build a frozen settings object, call one library function.

Every command prints where its output went; errors become one line and an exit code in one
place (:func:`agvviz.cli.common.handle_errors`). The typer app is :data:`agvviz.cli.main.app`
(its commands in :mod:`~agvviz.cli.record_run`, :mod:`~agvviz.cli.inspect`,
:mod:`~agvviz.cli.viewer`, :mod:`~agvviz.cli.compare`); the console script is
:func:`agvviz.__main__.main`, which installs the signal handlers (:mod:`agvviz.cli.interrupts`)
before the command line is imported — which is why this package's ``__init__`` imports nothing.
"""
