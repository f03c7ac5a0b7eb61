"""The one exception type users see (and the warnings about optional dataset parts).

Every check of user input (files, poses, shapes, caches, checkpoints) raises :class:`DepthnerfError` with a single
line that names the file and the problem. The CLI prints it as ``error: <message>`` and exits with status 2; a
Python API user gets the exception itself. In a multi-process job (torchrun) a refusal that every rank reaches alike
is printed once: rank 0 raises it as a :class:`DepthnerfError`, every other rank as a :class:`RefusedOnMain`, which
the CLI does not print (:func:`refusal`).
"""

import os


class DepthnerfError(Exception):
    """Bad user input or state: the message is one line naming the file and the problem."""


class RefusedOnMain(DepthnerfError):
    """What a rank other than 0 raises for a refusal that rank 0 raises too and prints (the same message): the CLI
    exits with status 2 without printing it, so the line appears once in a multi-process job's output."""


def launch_rank() -> int:
    """This process's rank in a torchrun job (``RANK`` where ``WORLD_SIZE`` > 1; 0 otherwise), known before the
    process group starts and without importing torch."""
    try:
        return int(os.environ.get("RANK", "0")) if int(os.environ.get("WORLD_SIZE", "1")) > 1 else 0
    except ValueError:
        return 0


def refusal(message: str, rank: int) -> DepthnerfError:
    """The exception rank ``rank`` raises for a refusal every rank reaches alike (from the same command line, or
    agreed on by all ranks): a :class:`DepthnerfError` on rank 0, which prints it, a :class:`RefusedOnMain` on the
    others, which do not."""
    return DepthnerfError(message) if rank == 0 else RefusedOnMain(message)


class DataWarning(UserWarning):
    """A problem in an *optional* part of a dataset (depth, mask, mesh): that part is not used for the object named;
    or required files read with a caveat (``rgb/`` images that are JPEG data under a ``.png`` name); one line naming
    the file. ``--strict`` (``strict=True`` in the readers) makes it a :class:`DepthnerfError`."""


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
