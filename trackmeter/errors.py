"""The one error type of the library.

Every failure that is the user's input (a malformed file, an image of the wrong size, a
value out of range) raises :class:`TrackmeterError` with a message that fits on one line and
names what was wrong. The command line turns it into that line on stderr and exit code 2; a
long-running process reports it and carries on.
"""

from __future__ import annotations

import re
import reprlib


class TrackmeterError(Exception):
    """Bad input or an unusable resource, with a one-line, user-facing message."""


def quoted(text: str, limit: int = 40) -> str:
    """``text`` quoted for a one-line message, its quoted form cut near ``limit`` characters with
    the length said: a corrupt file's field (thousands of NUL bytes, each quoted as 4) must not
    become the whole screen."""
    if len(repr(text)) <= limit + 2:
        return repr(text)
    head = text[:limit]
    while len(repr(head)) > limit + 2:
        head = head[:-1]
    return f"{head!r}... ({len(text)} characters)"


def quoted_name(name: str) -> str:
    """A file name quoted for a message, control characters such as NUL escaped (``repr``) and
    its bytes that are not UTF-8 written as ``\\xfe``, as the command line and the console
    show them (Python holds those bytes as the lone surrogates ``\\udcfe``, PEP 383)."""
    # An escape is preceded by an even number of backslashes: the name's own backslashes are
    # doubled by repr, and a name may hold the text "\\udcfe" itself.
    return re.sub(r"(?<!\\)((?:\\\\)*)\\udc([89a-f][0-9a-f])", r"\1\\x\2", repr(name))


def shown_value(value: object, limit: int = 60) -> str:
    """``repr(value)`` bounded for a one-line message: lists, mappings and strings cut by
    :mod:`reprlib` (a few items, a few levels), the whole cut near ``limit`` characters. A
    refused YAML value may be a list of ten thousand numbers, or an alias bomb whose full repr
    is hundreds of millions of characters and takes seconds to build."""
    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxtuple, short.maxdict, short.maxset = 3, 4, 4, 3, 4
    short.maxstring = short.maxother = limit
    text = short.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``"1 frame"``, ``"2 frames"``: a count with its noun in the right number."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
