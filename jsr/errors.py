"""Errors a user can fix. Their message is one line: what is wrong and what to do.

The CLI prints the message of any :class:`JsrError` on one line and exits non-zero (2);
every other exception is a bug: one "internal error" line, exit code 1, and its traceback in
the debug log (``-vv``).
"""


class JsrError(Exception):
    """Base class of errors caused by the user's input, config or output folder."""

    exit_code = 2


class InputError(JsrError):
    """A sequence, image, camera file or trajectory cannot be used as given."""


class ConfigError(JsrError):
    """A config file or a ``--set`` override is invalid (unknown key, wrong type, ...)."""


class OutputError(JsrError):
    """The output folder cannot be written (already holds results, not writable, ...)."""
