"""The library every part of vistrack shares.

Importing it first limits the pixels OpenCV decodes an image to, before any of its modules
loads OpenCV (:mod:`.imagelimit`).
"""

from . import imagelimit as _imagelimit  # noqa: F401 - sets OpenCV's limit as it loads
