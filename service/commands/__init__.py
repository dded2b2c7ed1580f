"""One module per ``socd`` subcommand; each exposes ``add_subparser(subparsers)``."""
