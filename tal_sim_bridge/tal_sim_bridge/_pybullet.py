"""PyBullet, imported without its C-level chatter (build time, URDF importer warnings)."""

from __future__ import annotations

import contextlib
import ctypes
import functools
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
    from pybullet_utils.bullet_client import BulletClient as _BulletClient


class BulletClient(_BulletClient):
    """pybullet_utils' client with its bound functions kept: its ``__getattr__`` runs ``inspect.isbuiltin`` and
    builds a ``functools.partial`` on every call (about 13 per physics step, 7 % of the bridge's CPU in a
    real-time tour, cProfile). A function is bound once, on first use, to this client's id; ``disconnect``
    forgets them (a later call fails as it did, instead of reaching a new connection that reuses the id)."""

    def __getattr__(self, name: str):
        attribute = super().__getattr__(name)
        if name == "disconnect":
            for key in [k for k, v in self.__dict__.items() if isinstance(v, functools.partial)]:
                del self.__dict__[key]
        elif isinstance(attribute, functools.partial):
            self.__dict__[name] = attribute
        return attribute


__all__ = ["BulletClient", "pybullet", "quiet_c_output"]
