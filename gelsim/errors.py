"""User-facing errors.

A :class:`GelsimError` carries one line that names the problem and the fix.
The command-line layer prints it as ``gelsim: error: <message>`` and exits
with status 2, without a traceback. Library users can catch it like any
``ValueError``.
"""


class GelsimError(ValueError):
    """Bad input or configuration; the message says what is wrong and how to fix it."""


def check_choice(what: str, value, choices, error: type[GelsimError] = GelsimError) -> None:
    """Raise ``error("unknown WHAT 'value'; choose one of a, b, c")`` unless ``value`` is in ``choices``
    (a collection of names)."""
    if value not in choices:
        raise error(f"unknown {what} {value!r}; choose one of {', '.join(choices)}")
