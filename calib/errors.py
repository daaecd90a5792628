"""The exception type for mistakes in what the user gave us, and the one case of it a caller adds advice to."""


class InputError(ValueError):
    """A user's input (file, argument, capture layout) is wrong.

    The message is one line naming the file or argument, what is wrong and what
    was expected; the command-line interface prints it without a traceback and
    exits with status 2. Programming errors keep their ordinary exception types.
    """


class NoImageSize(InputError):
    """A calibration format that stores no image sizes names a camera whose media give none (no video or images of
    it): the capture reader adds how to leave such a camera out."""
