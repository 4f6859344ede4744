"""Exceptions the libraries raise for a user's mistake (bad file, bad input).

The CLI turns a `UserInputError` into one line on stderr and exit status 2; anything else keeps its traceback,
because it is a bug.
"""


class UserInputError(ValueError):
    """Input supplied by the user is missing, malformed or out of range."""
