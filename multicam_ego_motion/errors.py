"""The one error type the command line turns into a one-line message and a non-zero exit."""


class UserError(Exception):
    """Bad input named in plain words: a missing file, a corrupt bag, an unknown scenario."""
