"""`TTError`, the base of every error tt raises for bad input.

It subclasses `ValueError`, so code that catches `ValueError` keeps working; it lives at the
bottom layer so that every layer can raise its typed errors under it. The CLI turns a
`TTError` into one ``error: ...`` line.
"""


class TTError(ValueError):
    """Bad input to tt: a flag, field, file or value that names what is wrong."""
