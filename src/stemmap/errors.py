"""Exceptions raised by stemmap.

Every message is a full sentence naming the file, field or value at fault and, where possible,
the fix. Low-level errors are wrapped with ``raise ... from``.
"""

from __future__ import annotations

__all__ = ["ConfigError", "InputError", "StemmapError"]


class StemmapError(Exception):
    """Base class of every error stemmap raises on purpose."""


class InputError(StemmapError, ValueError):
    """Input data (an array, a file, a message) is malformed: wrong shape, dtype, or content."""


class ConfigError(StemmapError, ValueError):
    """A configuration value or preset name is invalid."""
