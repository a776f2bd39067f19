"""Error hierarchy of apo: every error a user can cause is an :class:`ApoError`."""

from __future__ import annotations


class ApoError(Exception):
    """Base class of every error apo raises for bad input or an impossible request."""


class InputFormatError(ApoError, ValueError):
    """A file or value is malformed: the message names the file, line or field."""


class GeometryError(ApoError, ValueError):
    """A model is unusable: not closed, degenerate faces, inconsistent orientation."""


class TrackingLostError(ApoError, RuntimeError):
    """Perception lost an object and could not recover it."""


class OutputError(ApoError, OSError):
    """An output destination is unusable (a file, not writable, held by another writer)."""
