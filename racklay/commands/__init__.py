"""One module per `racklay` sub-command; each defines `register(subparsers)`."""
