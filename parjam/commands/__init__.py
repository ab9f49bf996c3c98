"""One module per ``parjam`` subcommand: ``add_parser(subparsers)`` and ``run(args)``."""
