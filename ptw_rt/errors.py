"""The error every command reports as one clear line, never as a traceback, and the exit codes.

Exit codes of ``ptw-rt`` (README, "Exit codes"):

* 0 ``EXIT_OK``: done.
* 1 ``EXIT_PARTIAL``: done, but not everything succeeded (``replay`` of several logs: some failed, each named in
  an ``error:`` line and its summary line; ``design --check``: a check failed; ``monitor``/``demo``: bad frames).
* 2 ``EXIT_USER``: a problem the user must fix, nothing done (configuration, design file, an input file, an
  argument; ``evaluate`` whose worker process died, since its tables need every ride). ``ptw-rt.service`` does not
  restart on it (``RestartPreventExitStatus=2``).
* 69 ``EXIT_UNAVAILABLE`` (sysexits' EX_UNAVAILABLE): ``run`` cannot open the CAN bus at start-up (no such
  interface, link down). systemd restarts the daemon: the interface may come later.
* 74 ``EXIT_OUTPUT`` (sysexits' EX_IOERR): an output cannot be written (``replay``'s, whatever its format;
  ``simulate``'s ride, ``report``'s plots, ``demo``'s logs and report): disk full, permission, a file where a
  directory is asked for.
"""

EXIT_OK = 0
EXIT_PARTIAL = 1
EXIT_USER = 2
EXIT_UNAVAILABLE = 69
EXIT_OUTPUT = 74


class UserFacingError(Exception):
    """Raised for problems the user can fix: configuration, design file, input files. ``exit_code``: what the
    command line exits with (``EXIT_USER`` unless a subclass says otherwise)."""

    exit_code = EXIT_USER


class OutputError(UserFacingError):
    """An output cannot be written (disk full, permission, not a file or not a directory)."""

    exit_code = EXIT_OUTPUT


def output_error(path, exc: OSError, kind: type[OutputError] = OutputError) -> OutputError:
    """The one line for an OSError writing ``path``, as ``kind`` (an OutputError)."""
    return kind(f"cannot write {path}: {exc.strerror or exc}")
