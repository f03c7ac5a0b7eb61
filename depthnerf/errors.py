"""The one exception type users see (and the warnings about optional dataset parts).

Every check of user input (files, poses, shapes, caches, checkpoints) raises :class:`DepthnerfError` with a single
line that names the file and the problem. The CLI prints it as ``error: <message>`` and exits with status 2; a
Python API user gets the exception itself.
"""


class DepthnerfError(Exception):
    """Bad user input or state: the message is one line naming the file and the problem."""


class DataWarning(UserWarning):
    """A problem in an *optional* part of a dataset (depth, mask, mesh): that part is not used for the object named;
    one line naming the file. ``--strict`` (``strict=True`` in the readers) makes it a :class:`DepthnerfError`."""


class DataNote(DataWarning):
    """Something in a dataset that is ignored on purpose (entries the layout does not know); one line."""


class UsageWarning(UserWarning):
    """A choice the user made on purpose that departs from how a model was trained (e.g. other depth weights
    through ``--depth-checkpoint``); one line naming the checkpoint."""


def format_data_warning(message: Warning | str, category: type[Warning]) -> str | None:
    """How the CLI prints a :class:`DataWarning` or :class:`UsageWarning` (``warning: ...``) or a
    :class:`DataNote` (``note: ...``); ``None`` for any other warning (printed the default way)."""
    if issubclass(category, UsageWarning):
        return f"warning: {message}"
    if not issubclass(category, DataWarning):
        return None
    return f"{'note' if issubclass(category, DataNote) else 'warning'}: {message}"
