"""slam6d: 6D SLAM for 3D laser scans after the Kurt3D method (Nüchter et al.).

The engine is a plain library: geometry, formats, octree, ICP, initial guess, loops, relaxation,
metrics, simulator, renderer and a steppable pipeline. It knows nothing of the web workbench.
"""

from slam6d.kernel_cache import ensure_kernel_cache

__version__ = "0.1.0"

ensure_kernel_cache()  # before any module defines a numba kernel: see slam6d.kernel_cache
