"""PyBullet, imported without its C-level chatter (build time, URDF importer warnings)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

_LIBC = ctypes.CDLL(None)


@contextlib.contextmanager
def quiet_c_output() -> Iterator[None]:
    """Silence C-level stdout and stderr (PyBullet prints its build time and URDF importer warnings)."""
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:  # no usable fds (some embedded runners): nothing to silence
        yield
        return
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
        os.dup2(devnull.fileno(), 2)
        try:
            yield
        finally:
            _LIBC.fflush(None)  # C stdio buffers would otherwise reach the restored streams later
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)


with quiet_c_output():
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

__all__ = ["BulletClient", "pybullet", "quiet_c_output"]
