"""The error every command reports as one clear line (exit code 2), never as a traceback."""


class UserFacingError(Exception):
    """Raised for problems the user can fix: configuration, design file, input files."""
