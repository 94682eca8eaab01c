"""``vistrack bench messages``: decoding and encoding the hot-path messages, msgspec against
the hand-written checks, in one process at one moment.

The messages a frame sends through the pipeline, as the services build them from the same
256x256 built-in frames: ``camera/frame`` (64 KiB), ``preprocessing/frame`` (the filtered
frame and ~1300 candidates) and ``motion/estimate`` (~100 features). For each: decoding with
validation, msgspec's fast path (what ``Message.decode`` runs) against the hand-written checks
alone (``unpack`` and the dataclass checks: what it ran before, and still runs to name the
field of a message msgspec refuses); and encoding a built message's fields, msgspec's encoder
(what ``pack`` runs) against ``msgpack.packb`` (the same bytes, checked). Then the sum over
one frame's trip (a frame and an estimate are decoded twice: by their consumer and by the
auto-tuner). Times are means over 500 calls, the best of interleaved rounds; nothing is
asserted about them. Building a message (its constructor's checks) is the same code either
way and is left out.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any, TextIO

import msgpack
import numpy as np

from ...common import synthetic
from ...common.messages import CmdVel, Estimate, Frame, PreFrame, pack, unpack
from ...common.params import TrackerParams
from ...common.vision import Tracker, preprocess, warm_up
from ..motion_estimation.service import estimate_message

#: How often each message is decoded and encoded on one frame's trip through the pipeline.
TRIP = {"camera/frame": (2, 1), "preprocessing/frame": (1, 1), "motion/estimate": (2, 1)}


def pipeline_messages(frames: list[np.ndarray]) -> tuple[Frame, PreFrame, Estimate, CmdVel]:
    """The messages the services send for frame 1 of ``frames`` (after frame 0), built as
    they build them."""
    params = TrackerParams()
    tracker = Tracker(params)
    for f in frames[:2]:
        pre = preprocess(f, params)
        est = tracker.update(pre)
    frame = Frame.from_image(frames[1], seq=1, stamp_ns=time.time_ns())
    return (frame,
            PreFrame(seq=1, stamp_ns=frame.stamp_ns, width=frame.width, height=frame.height,
                     data=pre.filtered, candidates=pre.candidates, strength=pre.strength,
                     params_id=1),
            estimate_message(est, seq=1, stamp_ns=frame.stamp_ns, params_id=1),
            CmdVel(seq=1, stamp_ns=frame.stamp_ns, vx=0.1, vy=-0.1, wz=0.0))


def _checks_decode(cls: Any, payload: bytes) -> object:
    """Decoding by the hand-written checks alone: what a refused message goes through."""
    return cls._from_map(unpack(payload))


def _us(fn: Callable[[], object], n: int = 500) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def bench_messages(out: TextIO = sys.stdout, rounds: int = 3) -> dict[str, float]:
    """Print the table; figures ``{key}_{decode|encode}_{msgspec|checks}_us`` per message key
    (``camera_frame``, ...) and ``trip_{msgspec|checks}_us``."""
    warm_up()
    msgs = pipeline_messages(synthetic.builtin_sequence(3))[:3]
    fig: dict[str, float] = {}
    print("# vistrack bench messages: decode (with validation) and encode, msgspec against "
          "the hand-written checks, same process and moment, us", file=out)
    for msg in msgs:
        payload = msg.encode()
        fields = {"v": 1, **msg._wire_fields()}
        if msgpack.packb(fields, use_bin_type=True) != payload:
            raise RuntimeError(f"{msg.KEY}: msgspec and msgpack wrote different bytes")
        cls: Any = type(msg)
        pairs: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {
            "decode": (partial(cls.decode, payload),
                       partial(_checks_decode, cls, payload)),
            "encode": (partial(pack, msg._wire_fields()),
                       partial(msgpack.packb, fields, use_bin_type=True))}
        name = msg.KEY.replace("/", "_")
        for what, (fast, slow) in pairs.items():
            a, b = [], []
            for _ in range(rounds):  # interleaved, so a slow spell falls on both
                a.append(_us(fast))
                b.append(_us(slow))
            fig[f"{name}_{what}_msgspec_us"] = min(a)
            fig[f"{name}_{what}_checks_us"] = min(b)
    for kind in ("msgspec", "checks"):
        fig[f"trip_{kind}_us"] = sum(
            d * fig[f"{k.replace('/', '_')}_decode_{kind}_us"]
            + e * fig[f"{k.replace('/', '_')}_encode_{kind}_us"] for k, (d, e) in TRIP.items())
    sizes = {m.KEY: len(m.encode()) for m in msgs}
    print(f"{'message':22s}{'bytes':>7s}  {'decode: msgspec':>16s}{'checks':>8s}{'ratio':>7s}  "
          f"{'encode: msgspec':>16s}{'msgpack':>8s}{'ratio':>7s}", file=out)
    for key in TRIP:
        n = key.replace("/", "_")
        d = (fig[f"{n}_decode_msgspec_us"], fig[f"{n}_decode_checks_us"])
        e = (fig[f"{n}_encode_msgspec_us"], fig[f"{n}_encode_checks_us"])
        print(f"{key:22s}{sizes[key]:7d}  {d[0]:16.1f}{d[1]:8.1f}{d[1] / d[0]:6.1f}x  "
              f"{e[0]:16.1f}{e[1]:8.1f}{e[1] / e[0]:6.1f}x", file=out)
    print(f"{'one frame trip':22s}{'':7s}  msgspec {fig['trip_msgspec_us']:.0f} us, checks "
          f"{fig['trip_checks_us']:.0f} us (decodes 2+1+2, encodes 1+1+1)", file=out)
    fig["trip_saved_us"] = fig["trip_checks_us"] - fig["trip_msgspec_us"]
    return fig


if __name__ == "__main__":
    bench_messages()
