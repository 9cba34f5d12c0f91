"""One module per ``dibrgs`` sub-command; each defines ``register(subparsers)``."""
