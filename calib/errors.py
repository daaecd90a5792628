"""The one exception type for mistakes in what the user gave us."""


class InputError(ValueError):
    """A user's input (file, argument, capture layout) is wrong.

    The message is one line naming the file or argument, what is wrong and what
    was expected; the command-line interface prints it without a traceback and
    exits with status 2. Programming errors keep their ordinary exception types.
    """
