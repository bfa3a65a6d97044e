"""Where numba keeps the compiled kernels of endo3d: outside the source tree.

numba caches a ``cache=True`` kernel beside its source (``__pycache__``) unless
``NUMBA_CACHE_DIR`` names another folder. A source tree is the wrong place: it
may be read-only (an installed package), it is shared by every worktree's
checkout, and ``git clean`` throws the cache away. So every package with numba
kernels calls :func:`use_kernel_cache` in its ``__init__``, before any kernel
module is imported: ``NUMBA_CACHE_DIR`` when the user set it, else
``$XDG_CACHE_HOME/endo3d/numba`` (``~/.cache/endo3d/numba``).

numba picks a kernel's cache folder when the kernel is decorated, from its
configuration, which it reads from the environment when numba is imported
(and re-reads on request). This module sets the environment variable and,
when numba is already imported, asks it to re-read; it never imports numba.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: The environment variable numba reads its cache folder from.
CACHE_DIR_VARIABLE = "NUMBA_CACHE_DIR"


def kernel_cache_dir() -> Path:
    """The folder compiled kernels go to.

    Returns:
        ``NUMBA_CACHE_DIR`` when set and not empty, else
        ``$XDG_CACHE_HOME/endo3d/numba`` (``~/.cache/endo3d/numba`` when
        ``XDG_CACHE_HOME`` is unset). The folder need not exist yet.
    """
    configured = os.environ.get(CACHE_DIR_VARIABLE, "")
    if configured:
        return Path(configured)
    cache_home = os.environ.get("XDG_CACHE_HOME", "") or str(Path.home() / ".cache")
    return Path(cache_home) / "endo3d" / "numba"


def use_kernel_cache() -> Path:
    """Point numba's kernel cache at :func:`kernel_cache_dir` for this process.

    Call before the modules defining ``cache=True`` kernels are imported.
    A ``NUMBA_CACHE_DIR`` the user set is kept. When the folder cannot be
    created, numba falls back to its own default (beside the source).

    Returns:
        The cache folder.
    """
    folder = kernel_cache_dir()
    os.environ[CACHE_DIR_VARIABLE] = str(folder)
    config = sys.modules.get("numba.core.config")
    reload_config = getattr(config, "reload_config", None)
    if callable(reload_config):
        reload_config()  # numba was imported before the variable was set
    return folder
