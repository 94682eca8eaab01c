"""Property-based tests of the service loops (hypothesis), driven in-process through the
MemoryNode seam with inputs that are valid but extreme: frames of one value, 1x1 to 64x64, a
single bright pixel, maximal noise; estimates with no feature or huge numbers; commands at
the limits of a float. Each loop runs once per test in a thread, and every generated input is
fed to it in turn, as a live service gets them: the loop never lets an exception out, answers
every input (an output, or a count in the status), and keeps going."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vistrack.common.bus import MemoryNode
from vistrack.common.messages import CmdVel, Estimate, Frame, Pose, PreFrame
from vistrack.common.params import MIN_VALID_NPI, TrackerParams
from vistrack.common.vision import preprocess
from vistrack.services import cli

IDLE_S = 20.0  # longest a loop may take over one input (a slow machine, a first compile)
FEW = settings(max_examples=40, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                       HealthCheck.too_slow])


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


class Running:
    """A service loop in a thread on a MemoryNode."""

    def __init__(self, service: str, loop, args) -> None:
        self.node = MemoryNode(service)
        self.error: BaseException | None = None
        self.seq = itertools.count()
        self.thread = threading.Thread(target=self._run, args=(loop, args), daemon=True)
        self.thread.start()

    def _run(self, loop, args) -> None:
        try:
            loop(self.node, args)
        except BaseException as e:  # noqa: BLE001 - recorded for the test to assert on
            self.error = e

    def feed(self, key: str, payload: bytes) -> None:
        """Deliver ``payload`` once the loop has subscribed, and wait until it is handled."""
        deadline = time.monotonic() + 60  # the first: warm-up and subscription
        while not self.node.feed(key, payload):
            assert self.thread.is_alive(), f"the loop ended: {self.error!r}"
            assert time.monotonic() < deadline, f"nothing subscribed to {key}"
            time.sleep(0.01)
        assert self.node.wait_idle(IDLE_S), f"{key}: not handled within {IDLE_S} s"
        assert self.thread.is_alive() and self.error is None, f"the loop ended: {self.error!r}"

    def counts(self) -> tuple[int, int, int]:
        s = self.node.status
        return s.published, s.rejected, s.failed

    def stop(self) -> None:
        self.node.stop.set()
        self.thread.join(10)
        self.node.close()
        assert self.error is None, f"the loop raised {self.error!r}"


@pytest.fixture(scope="module")
def running() -> Iterator[dict[str, Running]]:
    """Each loop started on first use, stopped at the end of the module."""
    started: dict[str, Running] = {}
    yield started
    for r in started.values():
        r.stop()


def start(running: dict[str, Running], name: str, *argv: str) -> Running:
    if name not in running:
        module = cli.COMMANDS[name][0]
        loop = __import__(f"vistrack.services.{module}", fromlist=["loop"]).loop
        running[name] = Running(name.replace("-", "_"), loop, parse(name, *argv))
    return running[name]


# -- generated inputs ----------------------------------------------------------------------

@st.composite
def extreme_images(draw, max_side: int = 64) -> np.ndarray:
    """A valid but extreme 8-bit grey image of 1x1 to 64x64."""
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    kind = draw(st.sampled_from(("one value", "bright pixel", "noise", "two values")))
    if kind == "one value":
        return np.full((h, w), draw(st.sampled_from((0, 1, 128, 254, 255))), np.uint8)
    if kind == "bright pixel":
        image = np.zeros((h, w), np.uint8)
        image[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = 255
        return image
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "noise":  # maximal: every grey level, independent pixels
        return rng.integers(0, 256, (h, w), dtype=np.uint8)
    return (rng.integers(0, 2, (h, w), dtype=np.uint8) * 255).astype(np.uint8)


FINITE = st.floats(allow_nan=False, allow_infinity=False)
HUGE = st.sampled_from((0.0, -0.0, 5e-324, 1e-300, -1e-300, 1e300, -1e300,
                        1.7976931348623157e308, -1.7976931348623157e308))
EXTREME = st.one_of(HUGE, FINITE)
POSITIVE = st.one_of(st.sampled_from((5e-324, 1e-300, 1e300, 1.7976931348623157e308)),
                     st.floats(min_value=5e-324, allow_nan=False, allow_infinity=False))


@st.composite
def extreme_estimates(draw, seq: int) -> bytes:
    """A valid estimate with extreme numbers, stamped a little before now (or long ago)."""
    npi = draw(st.integers(0, 3))
    features = [[i, draw(EXTREME), draw(EXTREME)] for i in range(npi)]
    age = draw(st.sampled_from((0.0, 0.001, 10.0, 1e6)))
    return Estimate(seq=seq, stamp_ns=time.time_ns() - int(age * 1e9), npi=npi,
                    xc=draw(EXTREME), yc=draw(EXTREME), xe=abs(draw(EXTREME)),
                    ye=abs(draw(EXTREME)), dx=draw(EXTREME), dy=draw(EXTREME),
                    scale=draw(POSITIVE), t_ms=abs(draw(EXTREME)), first=draw(st.booleans()),
                    features=features, params_id=0).encode()


def frame(image: np.ndarray, seq: int) -> bytes:
    return Frame.from_image(image, seq=seq, stamp_ns=time.time_ns()).encode()


def pre_frame(image: np.ndarray, seq: int) -> bytes:
    pre = preprocess(image, TrackerParams())
    return PreFrame(seq=seq, stamp_ns=time.time_ns(), width=image.shape[1],
                    height=image.shape[0], data=pre.filtered, candidates=pre.candidates,
                    strength=pre.strength, params_id=0).encode()


# -- the loops -------------------------------------------------------------------------

@FEW
@given(image=extreme_images())
def test_preprocessing_answers_every_extreme_frame(running, image):
    r = start(running, "preprocessing")
    published, rejected, failed = r.counts()
    r.feed(r.node.keys.frame, frame(image, next(r.seq)))
    # pre-processed (and said done: in memory something always listens), nothing failed
    assert r.counts() == (published + 2, rejected, failed)
    out = PreFrame.decode(r.node.published_on(r.node.keys.pre_frame)[-1])
    assert (out.height, out.width) == image.shape


@FEW
@given(images=st.lists(extreme_images(max_side=48), min_size=1, max_size=3))
def test_motion_estimation_answers_every_extreme_frame(running, images):
    r = start(running, "motion-estimation")
    for image in images:
        _, rejected, failed = r.counts()
        estimates = len(r.node.published_on(r.node.keys.estimate))
        r.feed(r.node.keys.pre_frame, pre_frame(image, next(r.seq)))
        # an estimate (and perhaps a motion/demand), nothing failed
        assert r.counts()[1:] == (rejected, failed)
        assert len(r.node.published_on(r.node.keys.estimate)) == estimates + 1
        est = Estimate.decode(r.node.published_on(r.node.keys.estimate)[-1])
        assert est.npi == len(est.features)
        assert est.valid == (est.npi >= MIN_VALID_NPI)


@FEW
@given(data=st.data())
def test_fuzzy_controller_answers_every_extreme_estimate(running, data):
    r = start(running, "fuzzy-controller")
    published, rejected, failed = r.counts()
    r.feed(r.node.keys.estimate, data.draw(extreme_estimates(next(r.seq))))
    now = r.counts()
    # a command, or a refusal (out of order, not finite once followed): never a failure,
    # and a command that goes out is a valid one
    assert now[2] == failed and now[0] + now[1] > published + rejected
    for payload in r.node.published_on(r.node.keys.cmd_vel)[-3:]:
        CmdVel.decode(payload)


@FEW
@given(data=st.data())
def test_auto_tuner_answers_every_extreme_frame_and_estimate(running, data):
    r = start(running, "auto-tuner", "--buffer", "4", "--min-interval", "0")
    rejected, failed = r.node.status.rejected, r.node.status.failed
    r.feed(r.node.keys.frame, frame(data.draw(extreme_images()), next(r.seq)))
    r.feed(r.node.keys.estimate, data.draw(extreme_estimates(next(r.seq))))
    assert (r.node.status.rejected, r.node.status.failed) == (rejected, failed)
    assert 1 <= r.node.status.extra["buffered"] <= 4


@FEW
@given(vx=EXTREME, vy=EXTREME, wz=EXTREME)
def test_simulator_camera_takes_extreme_commands_and_renders_on(running, vx, vy, wz):
    r = start(running, "camera", "--source", "sim", "--size", "16x16", "--fps", "200")
    frames = r.node.status.extra.get("frames", 0)
    r.node.feed(r.node.keys.cmd_vel, CmdVel(seq=next(r.seq), stamp_ns=time.time_ns(), vx=vx,
                                            vy=vy, wz=wz).encode())
    deadline = time.monotonic() + IDLE_S
    while r.node.status.extra.get("frames", 0) < frames + 3:  # the command taken, and on
        assert r.thread.is_alive() and r.error is None, f"the loop ended: {r.error!r}"
        assert time.monotonic() < deadline, "the simulator stopped rendering"
        time.sleep(0.005)
    assert r.node.status.failed == 0
    pose = Pose.decode(r.node.published_on(r.node.keys.pose)[-1])
    assert all(np.isfinite([pose.x, pose.y, pose.theta]))
