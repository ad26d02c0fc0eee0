"""Environment variables set for a block of code and put back after it."""
from __future__ import annotations

import os
from contextlib import contextmanager


@contextmanager
def restored_environ(*names):
    """Put the environment variables ``names`` back as they were when the block ends (unset where
    they were unset), whatever the block set them to: ``os.environ.update(...)`` inside it is undone."""
    saved = {k: os.environ.get(k) for k in names}
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
