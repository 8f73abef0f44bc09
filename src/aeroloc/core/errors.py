"""One exception type for every user-facing failure, so the CLI can print one line and exit non-zero."""


class AerolocError(Exception):
    """A problem with the user's input or environment (missing file, bad range, no weights ...).

    The message is shown to the user as is: name the file and the problem, and how to fix it if known.
    """


class WeightsNotFound(AerolocError):
    """Model weights are not available locally and could not be downloaded."""


class QueryImageError(AerolocError):
    """One query's image can't be matched (too small, of the wrong shape): that query is "not localized" with this
    message and a run over many goes on. Only for faults of the image itself, never of the database, the map or
    the environment, whose errors must end the run: a finished run's results are reused, and a transient fault
    recorded as a query's status would be reused with them."""
