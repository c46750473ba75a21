"""numba's BLAS check, answered without importing all of scipy.linalg.

The first numba call in a process - a kernel compiled or loaded from the cache alike - loads numba's
lowering registries, once. One of them, ``numba.np.arraymath``, checks as it is imported that a
BLAS is there, by importing ``scipy.linalg.cython_blas``. Python imports a submodule's package
first, and ``scipy.linalg``'s ``__init__`` imports every decomposition it offers and scipy's
array-API layer, which touches every numpy submodule on the way (numpy.f2py, numpy.testing,
numpy.ma, numpy.random, ...): ~0.15 s of CPU in every `slam6d run`, a tenth of a 10-scan session's
whole command (``benchmarks/startup.py``). numba itself uses nothing of it there: it reads the BLAS
functions' addresses from that one extension module, and only when it compiles a kernel that calls
BLAS (``np.dot``, ``np.linalg``), which none of the engine's kernels do (their 3x3 algebra is
written out).

:func:`load_blas_bindings` loads that extension module on its own, under its full name, before numba
asks for it; the import statement then finds it in ``sys.modules``. It is the very module
``scipy.linalg`` would load. ``import scipy.linalg`` works as before afterwards, and
``scipy.linalg.cython_blas`` is reached as an import (``import scipy.linalg.cython_blas``, ``from
scipy.linalg import cython_blas``), not as an attribute of a package that did not exist when it
loaded. Where anything is off - scipy.linalg loaded already, scipy missing, the extension not
where scipy's package says - it does nothing, and numba imports scipy.linalg as it always did.

The command line calls it first thing in the commands that run kernels (a fresh process each);
the workbench and the Dask workers live long enough not to notice the difference.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys

BLAS_BINDINGS = "scipy.linalg.cython_blas"
"""The module numba's ``ensure_blas`` imports (``numba/np/linalg.py``)."""


def load_blas_bindings() -> bool:
    """Load scipy's Cython BLAS bindings without the ``scipy.linalg`` package; whether it did.

    Call it before numba's first call in the process. It imports the ``scipy`` package itself
    (~0.02 s, which numba's check reads its build configuration from anyway), never ``scipy.linalg``."""
    if BLAS_BINDINGS in sys.modules or "scipy.linalg" in sys.modules:
        return False
    try:
        package = importlib.util.find_spec("scipy.linalg")  # imports scipy, not scipy.linalg
    except ImportError:
        return False
    if package is None or not package.submodule_search_locations:
        return False
    spec = importlib.machinery.PathFinder.find_spec(BLAS_BINDINGS, list(package.submodule_search_locations))
    if spec is None or spec.loader is None:
        return False
    module = importlib.util.module_from_spec(spec)
    sys.modules[BLAS_BINDINGS] = module
    try:
        spec.loader.exec_module(module)
    except Exception:
        del sys.modules[BLAS_BINDINGS]  # numba's own import then tries again, through the package
        return False
    return True
