"""The one exception the command line turns into a single error line."""


class InputError(Exception):
    """A bad input found before (or instead of) the work: the message names
    the file or flag and says what to do."""
