"""The machinery of focusmap: run folders, artifacts, settings, the stage registry and runner, Rerun helpers.

Nothing in this package knows about robotics; stages live in :mod:`stages`.
"""

__version__ = "0.1.0"
