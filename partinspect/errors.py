"""The one exception type that reaches the user as a clear line, not a traceback."""


class InputError(Exception):
    """A bad input: the run cannot be made (exit code 2).

    Parameters
    ----------
    path : str or os.PathLike or None
        The file or folder at fault; named first in the message.
    problem : str
        What is wrong with it, in one line.

    Examples
    --------
    >>> str(InputError("images/left.png", "image is 640x480, calibration says 2448x2048"))
    'images/left.png: image is 640x480, calibration says 2448x2048'
    """

    def __init__(self, path, problem):
        self.path = None if path is None else str(path)
        self.problem = " ".join(str(problem).split())
        super().__init__(self.problem if self.path is None else f"{self.path}: {self.problem}")
