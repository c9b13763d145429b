"""Errors that several layers raise and the trainer and the command line tell apart."""
from __future__ import annotations


class NonFiniteError(ValueError):
    """A tensor that must be finite holds NaN or infinite values (a diverging step, a broken input)."""


class TrainingFailed(RuntimeError):
    """Training stopped on a failure; the message says where the last good checkpoint and the failed state are."""


class DeviceUnavailable(RuntimeError):
    """The requested device or a backend it needs is not available; the message says how to get it."""
