"""One module per ``imunoise`` sub-command; each exposes ``register(subparsers)``."""
