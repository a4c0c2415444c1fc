"""Error types whose message is one clear line for the user (the CLI prints it as is)."""

from __future__ import annotations


class MideepbasisError(Exception):
    """Base of every error that is the user's to fix: bad input, missing set-up."""


class InputError(MideepbasisError, ValueError):
    """A file or value given by the user is unusable; the message names it and the problem."""
