"""stam's user-facing error.

:class:`StamError` carries one line that names the problem and the fix, like gelsim's
:class:`~gelsim.errors.GelsimError`, of which it is a subclass: the shared command-line dispatcher
(``gelsim.cli.dispatch``) prints either as ``stam: error: <message>`` and exits with status 2.
stam raises StamError for its own checks (datasets, configs, checkpoints, models); errors from
gelsim itself (decoding a video) stay GelsimError, so ``except GelsimError`` catches both.
"""
from gelsim.errors import GelsimError


class StamError(GelsimError):
    """Bad input or configuration in stam; the message says what is wrong and how to fix it."""
