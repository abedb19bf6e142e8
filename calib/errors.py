"""The error type every layer raises for bad user input.

The CLI turns a :class:`UserError` into one line on stderr and exit code 2; anything
else is a bug and keeps its traceback.
"""


class UserError(Exception):
    """Bad input from the user: a clear one-line message saying what is wrong and what to do."""
