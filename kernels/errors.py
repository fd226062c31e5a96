"""The base of tt's errors."""


class TTError(ValueError):
    """Bad input or a bad file, told in one line naming the flag, field or file."""
