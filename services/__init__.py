"""vistrack's services, launcher and tools.

A module here may import OpenCV before anything of ``common``: ``common`` is imported first,
so that OpenCV loads with vistrack's limit on the pixels it decodes
(:mod:`vistrack.common.imagelimit`).
"""

import vistrack.common  # noqa: F401 - before any module here loads OpenCV
