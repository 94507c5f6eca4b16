"""One module per `python -m gear` command; each defines `register(subparsers)`."""
