"""The one error type the data layer raises for bad input."""
from __future__ import annotations


class SceneError(ValueError):
    """A scene folder, file or camera that cannot be loaded.

    The message always names the offending path (or camera id) and, where one exists, the fix.
    """
