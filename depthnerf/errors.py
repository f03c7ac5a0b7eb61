"""The one exception type users see (and the warnings about optional dataset parts).

Every check of user input (files, poses, shapes, caches, checkpoints) raises :class:`DepthnerfError` with a single
line that names the file and the problem. The CLI prints it as ``error: <message>`` and exits with status 2; a
Python API user gets the exception itself. In a multi-process job (torchrun) a refusal that every rank reaches alike
is printed once: rank 0 raises it as a :class:`DepthnerfError`, every other rank as a :class:`RefusedOnMain`, which
the CLI does not print (:func:`refusal`).
"""

import os
import re

_WORKER_TRACEBACK = re.compile(r"Caught \w+ in DataLoader worker process \d+\.\n"
                               r"Original Traceback \(most recent call last\):\n")
"""How torch's ``ExceptionWrapper.reraise`` begins the message of an exception it re-raises in the main process."""


class DepthnerfError(Exception):
    """Bad user input or state: the message is one line naming the file and the problem.

    Raised in a DataLoader worker, it keeps that line in the main process: torch re-raises a worker's exception as
    its type called with ``Caught <type> in DataLoader worker process N.``, a new line and the formatted traceback
    (the instance itself does not cross the process boundary), whose last line is ``<module>.<class>: <message>``;
    the constructor takes the message back from there (:func:`worker_message`), so the CLI prints one line.
    """

    def __init__(self, *args: object) -> None:
        if len(args) == 1 and isinstance(args[0], str):
            args = (worker_message(args[0], type(self)),)
        super().__init__(*args)


def worker_message(text: str, kind: type[BaseException]) -> str:
    """The one-line message of a ``kind`` exception raised in a DataLoader worker, taken from the ``text`` torch
    re-raises it with in the main process (see :class:`DepthnerfError`); any other ``text`` unchanged."""
    if not _WORKER_TRACEBACK.match(text):
        return text
    prefix = f"{kind.__module__}.{kind.__qualname__}: "
    last = text.rstrip("\n").rsplit("\n", 1)[-1]
    return last[len(prefix):] if last.startswith(prefix) else text


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
