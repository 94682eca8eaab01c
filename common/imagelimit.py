"""How many pixels an image may decode to: OpenCV's own limit, set before OpenCV loads.

A compressed image says its size in its header, and a small one can claim a huge size: a
PNG of 875 KB decodes to 30000x30000 px, which ``cv2.imdecode`` allocated (a peak RSS of
1.76 GB, 5 to 7 s) before any check of ours saw the image. OpenCV checks the header's size
against ``OPENCV_IO_MAX_IMAGE_PIXELS`` (default 2^30) before it allocates, in ``imread`` and
``imdecode``, but reads the variable once, when it loads: set after ``import cv2`` it does
nothing. So importing ``vistrack.common`` (and ``vistrack.services``, whose modules may
import OpenCV before anything of ``common``) sets it to :data:`DEFAULT_PIXELS` unless the
environment sets it already, and every process of vistrack, its children too, decodes no
image larger than that: a ROS 2 ``CompressedImage``, an image file, a simulator texture. An
image refused so raises ``cv2.error`` from the header alone; :func:`decode` says it in
words. Importing this module does not import OpenCV.

A process that loaded OpenCV before this module (a program of its own that imports ``cv2``
first) keeps OpenCV's default, 2^30 px: there :func:`decode` refuses, once decoded, what
OpenCV would have refused.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from typing import TypeVar

_T = TypeVar("_T")

#: The variable OpenCV reads, once, when it loads.
VARIABLE = "OPENCV_IO_MAX_IMAGE_PIXELS"
#: vistrack's limit: 8192x8192 px, 4 times the pixels of the largest ``camera/frame``
#: (4096x4096) and more than a 60 MP camera's; a grey image of it is 64 MiB decoded.
DEFAULT_PIXELS = 1 << 26


#: the suffixes OpenCV's parser of the variable takes (any case), and what each multiplies by
_SUFFIXES = {"": 1, "kb": 1 << 10, "mb": 1 << 20, "gb": 1 << 30}


def parse_limit(given: str) -> int | None:
    """The pixels a value of ``OPENCV_IO_MAX_IMAGE_PIXELS`` allows, read as OpenCV reads it:
    a whole number with an optional suffix KB, MB or GB in any case (``100MB`` is 104857600;
    0 refuses every image); None for what OpenCV does not read (``50M``, ``1e9``: it aborts
    the process as it loads)."""
    match = re.fullmatch(r"(\d+)([kKmMgG][bB])?", given.strip())
    if match is None:
        return None
    return int(match[1]) * _SUFFIXES[(match[2] or "").lower()]


def _limit() -> int:
    """The limit OpenCV runs with in a process whose OpenCV loads after this: ours, or the
    environment's own (a value OpenCV does not read: ours, though OpenCV will not run)."""
    given = parse_limit(os.environ.setdefault(VARIABLE, str(DEFAULT_PIXELS)))
    return DEFAULT_PIXELS if given is None else given


MAX_PIXELS = _limit()


def _side() -> str:
    side = int(MAX_PIXELS ** 0.5)
    if side == 0:
        return "none"
    return f"{side}x{side}" if side * side == MAX_PIXELS else f"{MAX_PIXELS / 1e6:.1f} MP"


def decode(what: str, read: Callable[[], _T], error: type[ValueError] = ValueError) -> _T:
    """``read()``, a ``cv2.imread`` or ``cv2.imdecode`` of ``what`` (e.g. ``compressed image
    (png, 874852 bytes)``), with an image larger than the limit refused as ``error`` in words:

    * by OpenCV from the header, before it allocates, where it loaded after this module:
      ``... decodes to more than the 67108864 px (8192x8192) an image may have
      (OPENCV_IO_MAX_IMAGE_PIXELS): refused from its header``.
      OpenCV's own ``cv2.error`` names neither size nor limit, only its check
      (``validateInputImageSize``), so the size is not known, only that it is more;
    * once decoded where not, naming the size: ``... is 9000x9000 px, more than ...``.

    Another ``cv2.error`` is raised as it is; what ``read`` returns (None for an image that
    does not decode) is returned.
    """
    import cv2  # here: what calls this has loaded it, and importing vistrack need not

    limit = f"the {MAX_PIXELS} px ({_side()}) an image may have ({VARIABLE})"
    try:
        image = read()
    except cv2.error as e:
        if "validateInputImageSize" not in str(e):
            raise
        raise error(f"{what} decodes to more than {limit}: refused from its header") from None
    shape = getattr(image, "shape", None)
    if shape is not None and shape[0] * shape[1] > MAX_PIXELS:
        raise error(f"{what} is {shape[1]}x{shape[0]} px, more than {limit}")
    return image
