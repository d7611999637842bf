"""User-facing errors.

A :class:`GelsimError` carries one line that names the problem and the fix.
The command-line layer prints it as ``gelsim: error: <message>`` and exits
with status 2, without a traceback. Library users can catch it like any
``ValueError``.
"""


class GelsimError(ValueError):
    """Bad input or configuration; the message says what is wrong and how to fix it."""
