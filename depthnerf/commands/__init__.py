"""One module per ``depthnerf`` subcommand: ``add_arguments(parser)`` and ``run(args) -> int``.

Commands parse arguments and call into the pipeline packages; they hold no pipeline logic themselves. A module
that sets ``ACCEPTS_OVERRIDES = True`` receives unknown ``--a.b value`` pairs in ``args.overrides``.
"""
