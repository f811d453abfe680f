"""Errors raised by the core. Every bad-input path raises :class:`InputError` with a message
that names the file (where there is one) and the offending element."""


class RetargetError(Exception):
    """Base class of every error the core raises on purpose."""


class InputError(RetargetError, ValueError):
    """Bad input: a malformed file, a wrong shape, a NaN, a non-manifold mesh, ...

    ``source`` is the file or object the problem was found in (may be empty) and
    ``element`` names the part of it (a joint, a field, a face)."""

    def __init__(self, message: str, *, source: str | None = None, element: str | None = None):
        self.source = source or ""
        self.element = element or ""
        where = ""
        if source:
            where += f"{source}: "
        if element:
            where += f"{element}: "
        super().__init__(where + message)
