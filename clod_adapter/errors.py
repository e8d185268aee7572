"""The one exception type for bad user input (:class:`InputError`): a file, a folder or a flag
that cannot be used. The command lines report it on one line with exit status 2; any other
exception is a bug and ends with its traceback and exit status 1 (``clod_adapter.cli.common.run_cli``)."""


class InputError(ValueError):
    """Bad user input (a file, a folder or a flag); the message is one line naming it."""
