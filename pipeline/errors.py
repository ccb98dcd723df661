"""The one exception type for bad input: its message names the file, variable or key."""


class BTFError(Exception):
    """Bad input or an impossible request; the CLI prints the message and exits non-zero."""
