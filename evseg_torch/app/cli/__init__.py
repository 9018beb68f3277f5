"""The ``evseg`` command line: wiring over the application layer, the pipeline, io, synthetic scenes and
evaluation, with no logic of its own.

:mod:`~evseg_torch.app.cli.entry` assembles the parser and holds :func:`main`; each command is one
module with ``add_parser`` and ``run``: :mod:`~evseg_torch.app.cli.segment`,
:mod:`~evseg_torch.app.cli.demo`, :mod:`~evseg_torch.app.cli.simulate` and
:mod:`~evseg_torch.app.cli.evaluate` (its protocols in ``evaluate_synthetic``, ``evaluate_eed``,
``evaluate_evimo`` and ``evaluate_labelled``). :mod:`~evseg_torch.app.cli.options` holds the options
and argument types the commands share, :mod:`~evseg_torch.app.cli.reports` the evaluations' shared
output.
"""

from evseg_torch.app.cli.entry import main

__all__ = ["main"]
