"""Pieces the command lines share: one-line usage errors and checked numeric options.

Every command line of the package reports bad input as one line naming the option and what was
expected, with exit status 2 (docs/cli.md).  Layer 0 (base): standard library only.
"""

import argparse
import math
import os

EXIT_BAD_INPUT = 2


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (the option and what was expected), exit status 2."""

    def error(self, message: str):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see --help)\n")


def user_path(text: str) -> str:
    """An argparse ``type`` for a path: a leading ``~`` is the home folder, as the shell would have it
    (a shell leaves ``--out=~/x`` and a quoted ``"~/x"`` alone, and ``./~/x`` is a trap to delete)."""
    return os.path.expanduser(text)


def number_in(name: str, low: float, high: float, integer: bool = False, low_open: bool = False,
              interval: str = "", hint: str = ""):
    """argparse type: a finite number (an integer if ``integer``) in [low, high], or (low, high]
    when ``low_open``; anything else is refused with a message naming ``name`` and the range
    (written as ``interval`` when given, e.g. "[0, 2**63 - 1]"), followed by ``hint`` in brackets."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{name} must be {'an integer' if integer else 'a number'}, got '{text}'") from None
        inside = (low < value if low_open else low <= value) and value <= high
        if not (math.isfinite(value) and inside):
            written = interval or f"{'(' if low_open else '['}{low:g}, {high:g}]"
            raise argparse.ArgumentTypeError(
                f"{name} {text}: must be {'an integer' if integer else 'a finite number'} in {written}"
                + (f" ({hint})" if hint else ""))
        return value

    return parse


EXIT_INTERRUPTED = 130


def interruptible(main, prog: str) -> int:
    """Run ``main()``; Ctrl-C or SIGTERM (:func:`stop_on_sigterm_as_on_ctrl_c`) prints one line and
    returns 130 instead of a traceback (or, for SIGTERM, a silent death that left scratch folders).

    For commands whose writes are atomic (a new file or folder renamed into place at the end),
    so an interruption leaves nothing half-written."""
    import sys

    stop_on_sigterm_as_on_ctrl_c()
    escape_what_output_cannot_encode()
    try:
        code = main()
        sys.stdout.flush()  # here, not at exit, so that a closed pipe is caught below
        return code
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing was left half-written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into `head` or a pager that quit: stop quietly, as Unix tools do
        silence_stdout()
        return 0


def escape_what_output_cannot_encode() -> None:
    """Write characters the output's encoding lacks as escapes (``\\u0141``) instead of stopping the
    command with a UnicodeEncodeError: Windows encodes redirected output in its ANSI code page, so
    a non-ASCII folder name printed to a log file ended a run with a traceback."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        if stream is not None and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def stop_on_sigterm_as_on_ctrl_c() -> None:
    """Handle SIGTERM (a batch scheduler's time limit, ``kill``) as Ctrl-C: KeyboardInterrupt in
    the main thread, so a run stops as documented for Ctrl-C (its last checkpoint kept, one line
    saying how to resume) instead of dying without a word."""
    import signal
    import threading

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():  # signal.signal works only there
        signal.signal(signal.SIGTERM, interrupt)


def silence_stdout() -> None:
    """Point standard output at /dev/null after its reader went away, so that the flush at exit
    does not raise a second BrokenPipeError."""
    import os
    import sys

    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
