"""The one error type of the library.

Every failure that is the user's input (a malformed file, an image of the wrong size, a
value out of range) raises :class:`TrackmeterError` with a message that fits on one line and
names what was wrong. The command line turns it into that line on stderr and exit code 2; a
long-running process reports it and carries on.
"""

from __future__ import annotations


class TrackmeterError(Exception):
    """Bad input or an unusable resource, with a one-line, user-facing message."""
