"""The ``prml2`` command line: one module per subcommand (cantools style).

Each subcommand module defines ``HELP`` (one line), ``NEEDS`` (optional modules it
requires, with the extra that provides them), ``add_arguments(parser)`` and
``run(args) -> int``. Modules import their heavy dependencies inside ``run`` so that
``prml2 --help`` stays fast and works without the optional extras.
"""
