"""One module per CLI verb: ``add_parser(subparsers) -> parser`` and ``run(args) -> int``."""
