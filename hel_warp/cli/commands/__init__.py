"""One module per ``hel-warp`` subcommand: ``add_parser(subparsers)`` and ``run(args)``."""
