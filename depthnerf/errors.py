"""The one exception type users see.

Every check of user input (files, poses, shapes, caches, checkpoints) raises :class:`DepthnerfError` with a single
line that names the file and the problem. The CLI prints it as ``error: <message>`` and exits with status 2; a
Python API user gets the exception itself.
"""


class DepthnerfError(Exception):
    """Bad user input or state: the message is one line naming the file and the problem."""
