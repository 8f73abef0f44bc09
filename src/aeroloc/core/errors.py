"""One exception type for every user-facing failure, so the CLI can print one line and exit non-zero."""


class AerolocError(Exception):
    """A problem with the user's input or environment (missing file, bad range, no weights ...).

    The message is shown to the user as is: name the file and the problem, and how to fix it if known.
    """


class WeightsNotFound(AerolocError):
    """Model weights are not available locally and could not be downloaded."""
