"""The error every command reports as one clear line, never as a traceback, and the exit codes.

Exit codes of ``ptw-rt`` (README, "Exit codes"):

* 0 ``EXIT_OK``: done.
* 1 ``EXIT_PARTIAL``: done, but not everything succeeded (``replay`` of several logs: some failed, each named in
  an ``error:`` line and its summary line; ``design --check``: a check failed; ``monitor``/``demo``: bad frames).
* 2 ``EXIT_USER``: a problem the user must fix, nothing done (configuration, design file, an input file, an
  argument). ``ptw-rt.service`` does not restart on it (``RestartPreventExitStatus=2``).
* 69 ``EXIT_UNAVAILABLE`` (sysexits' EX_UNAVAILABLE): ``run`` cannot open the CAN bus at start-up (no such
  interface, link down). systemd restarts the daemon: the interface may come later.
* 74 ``EXIT_OUTPUT`` (sysexits' EX_IOERR): an output of ``replay`` cannot be written, whatever its format (disk
  full, permission, a directory).
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
