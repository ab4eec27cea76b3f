"""Settings changed for the length of a block and put back afterwards, also on errors."""
from __future__ import annotations

import contextlib


@contextlib.contextmanager
def temporarily(changes):
    """Set each (owner, attribute, value) of `changes` for the block, in order (a generator sees the settings made
    before it); every one comes back afterwards, in reverse order, so an owner changed twice ends as it was."""
    saved = []
    try:
        for owner, name, value in changes:
            saved.append((owner, name, getattr(owner, name)))
            setattr(owner, name, value)
        yield
    finally:
        for owner, name, value in reversed(saved):
            setattr(owner, name, value)
