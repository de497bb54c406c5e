"""The SensorBox error tree.

It lives in the bottom package so every layer can raise and catch it. Library
code raises these with a message that names the file, key, topic or value at
fault and what was expected; only the CLI turns them into an exit code.
"""

from __future__ import annotations


class SensorboxError(Exception):
    """Base of every error SensorBox raises on purpose."""


class CalibrationError(SensorboxError):
    """A camera model, Kalibr camchain or rig file is malformed or inconsistent."""


class WriteError(SensorboxError):
    """The operating system refused a write (disk full, read-only or missing folder, permissions), or an
    output path is a device, FIFO or socket. The message names the file; the CLI exits 3 for it."""
