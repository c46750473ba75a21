"""slam6d: 6D SLAM for 3D laser scans after the Kurt3D method (Nüchter et al.).

The engine is a plain library: geometry, formats, octree, ICP, initial guess, loops, relaxation,
metrics, simulator, renderer and a steppable pipeline. It knows nothing of the web workbench.
"""

__version__ = "0.1.0"
