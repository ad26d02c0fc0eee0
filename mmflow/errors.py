"""Exceptions with messages that name the thing, the field and the fix."""


class MmflowError(Exception):
    """Base class for every error mmflow raises on purpose."""


class InputError(MmflowError, ValueError):
    """Bad user input: a file, a field or a value that cannot be used.

    Parameters
    ----------
    what : str
        The file or object at fault.
    field : str
        The field, column or parameter at fault.
    problem : str
        What is wrong.
    fix : str
        What the user should do.
    """

    def __init__(self, what, field, problem, fix):
        self.what, self.field, self.problem, self.fix = what, field, problem, fix
        super().__init__(f"{what}: field '{field}': {problem}. Fix: {fix}")

    def __reduce__(self):  # survive pickling between dask workers and the driver
        return type(self), (self.what, self.field, self.problem, self.fix)


class CoverageError(InputError):
    """Time-ordered data do not cover enough of the sidereal day."""


class StaleOutputError(MmflowError):
    """A stage's stored output was made from other inputs or another configuration."""
