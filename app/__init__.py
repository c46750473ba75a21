"""The web workbench over the slam6d engine (FastAPI pages and REST, viser 3D views)."""
