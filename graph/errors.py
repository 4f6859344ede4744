"""Exceptions the libraries raise for a user's mistake (bad file, bad input).

The CLI turns a `UserInputError` into one line on stderr and exit status 2; anything else keeps
its traceback, because it is a bug.
"""


from macroloc.common.errors import UserInputError  # one class for both libraries and the CLI


class BuildingError(UserInputError):
    """A building model cannot be read or holds nothing usable."""
