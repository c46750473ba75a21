"""The workbench's 3D view (viser): one view per open session, its parts and its panels.

Start at :mod:`app.view.session_view`; :mod:`app.view.registry` starts views on demand and
:mod:`app.view.proxy` forwards each view's viser client through the workbench's own port.
"""
