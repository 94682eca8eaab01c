"""fuzzy-controller: turn each motion estimate into a velocity command that cancels the
apparent motion (keeps the target centred and at the reference distance).

Reads   ``vistrack/<robot>/motion/estimate``  (latest only; the same one again, ``seq`` and
        ``stamp_ns`` of the last one used, is ignored: motion-estimation answered a frame a
        camera in lockstep sent again)
Writes  ``vistrack/<robot>/control/cmd_vel``  (reliable; zero with ``stale: true`` while the
        estimates are older than the watchdog bound, not ``valid``, or too few features are
        tracked)

The set point (centroid and scale) is captured from the first estimate of each track, unless
``--x-ref`` fixes it. A track begins with ``first``, or where ``seq`` goes back (the camera
restarted; its first estimate may have been overwritten at the latest-only input). The law is
the fuzzy rule base of ``rules.py`` compiled into a control surface (``--law fuzzy``, default)
or a plain proportional law (``--law proportional``).
"""

from __future__ import annotations

import argparse
import logging
import math
import time

from ...common.bus import Node
from ...common.messages import MAX_SIDE, Estimate, encode_cmd_vel
from ...common.params import BOUNDS, MIN_VALID_NPI
from ..runtime import (
    NO_ESTIMATE,
    REJECTED_LOG_S,
    add_service_args,
    came_late,
    decode_or_reject,
    dispatch,
    ready,
    reject,
    serve,
    starts_track,
)
from ..usage import add_number
from .control import (
    MIN_NPI_RANGE,
    STALE_AFTER_RANGE,
    STOP,
    X_REF_RANGE,
    ControllerConfig,
    FuzzyController,
    FuzzySurface,
    ProportionalController,
    ProportionalGains,
)
from .rules import FuzzyLimits

log = logging.getLogger("vistrack.fuzzy_controller")

STALE_REPEAT_S = 0.1  # how often the stop is repeated while the estimates are stale
# The watchdog measures an estimate's age from its stamp (the capture time), so it assumes
# the camera's clock and this one agree to well under --stale-after. An estimate stamped
# further ahead than this is refused: accepted, it would never look stale (its command would
# be kept however old it got), and every later estimate would look out of order.
MAX_AHEAD_S = 1.0


class CameraClock:
    """``--clock camera``: the time is the camera's, the newest estimate's stamp plus the host
    time since it came in. A simulator in lockstep stamps its frames on a simulated clock that
    runs as fast as the pipeline (about 6x real time here): on the host's clock its estimates
    were soon more than :data:`MAX_AHEAD_S` ahead and refused, and the simulator waited its
    ``--ack-timeout`` for a command that never came, 13 times in a 20 s scenario. On this clock
    an estimate is never ahead, and the watchdog still stops the robot when none has come for
    ``--stale-after`` s of host time."""

    def __init__(self) -> None:
        self._stamp: float | None = None
        self._at = 0.0

    def now(self) -> float:
        if self._stamp is None:
            return time.time()
        return self._stamp + (time.monotonic() - self._at)

    def arrived(self, stamp_s: float, restart: bool = False) -> None:
        """An estimate stamped ``stamp_s`` came in. ``restart``: the camera started again (a
        new track), its clock possibly from an earlier time: the clock follows it back. Else
        the clock only moves forward."""
        if restart or self._stamp is None or stamp_s > self._stamp:
            self._stamp, self._at = stamp_s, time.monotonic()

# Full command at a tenth of a half-width off centre (12.8 px at 256) and at a 10 % size
# error: the whole-image limits of the rule base's defaults left the robot trailing a target
# that moves at 0.24 m/s by ~14 px (README, "The fuzzy controller"). The centroid
# defuzzification of the outer terms NB and PB (-1, -1, -0.5) and (0.5, 1, 1) peaks at 5/6 of
# vy_max and vx_max: the fuzzy law commands at most 0.667 m/s, the proportional one 0.8.
LIMITS = FuzzyLimits(ex_max=0.1, dex_max=0.3, ez_max=0.1, dez_max=0.3, vy_max=0.8, vx_max=0.8)
#: The image width, px, that normalises the centring error where neither --image-width nor
#: the estimate (``width``; an older publisher's has none) gives one.
DEFAULT_WIDTH = 256.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--law", choices=("fuzzy", "proportional"), default="fuzzy",
                        help="control law (default fuzzy)")
    add_number(parser, "--image-width", lo=8, hi=MAX_SIDE, default=None, metavar="PX",
               help="image width used to normalise the centring error, %(allowed)s "
                    f"(default: the width each estimate gives, else {DEFAULT_WIDTH:g})")
    add_number(parser, "--x-ref", lo=X_REF_RANGE[0], hi=X_REF_RANGE[1], default=None,
               metavar="PX", help="set-point centroid x, %(allowed)s (default: captured from "
                                  "the first estimate)")
    add_number(parser, "--stale-after", lo=STALE_AFTER_RANGE[0], hi=STALE_AFTER_RANGE[1],
               lo_open=True, default=0.3, metavar="S",
               help="watchdog: stop the robot when estimates are older, %(allowed)s "
                    "(default 0.3)")
    add_number(parser, "--min-npi", lo=MIN_NPI_RANGE[0], hi=MIN_NPI_RANGE[1], integer=True,
               default=5, metavar="N",
               help="stop the robot when fewer features are tracked, %(allowed)s (default 5; "
                    "0: never)")
    parser.add_argument("--clock", choices=("host", "camera"), default="host",
                        help="the watchdog's clock: this host's (default; the camera's must "
                             "agree with it), or the camera's, taken from the estimates' "
                             "stamps (a simulator's simulated clock, with --lockstep)")
    add_service_args(parser)


def make_controller(args: argparse.Namespace) -> FuzzyController | ProportionalController:
    config = ControllerConfig(stale_after_s=args.stale_after, min_npi=args.min_npi,
                              x_ref=args.x_ref)
    if args.law == "fuzzy":
        return FuzzyController(FuzzySurface.compile(LIMITS), config)
    return ProportionalController(ProportionalGains(
        kx=LIMITS.vy_max / LIMITS.ex_max, kz=LIMITS.vx_max / LIMITS.ez_max,
        vy_max=LIMITS.vy_max, vx_max=LIMITS.vx_max), config=config)


#: Estimates in a row that came older than --stale-after before that is said (once).
LATE_SAID_AFTER = 30


def loop(node: Node, args: argparse.Namespace) -> None:
    ctrl = make_controller(args)
    most = int(BOUNDS["max_features"][1])
    if args.min_npi > most:
        log.warning("--min-npi %d is more features than a tracker ever holds (max_features "
                    "is at most %d): every estimate will be answered with a stop",
                    args.min_npi, most)
    late_in_a_row = 0
    node.subscribe(node.keys.estimate, latest=True)
    node.advertise(node.keys.cmd_vel, reliable=True)
    seq = 0
    # the watchdog's own times are the host's monotonic clock: a step of the wall clock (an
    # NTP correction, date -s) back by 20 s made every age negative, and the robot went on
    # with its last move for 18 s after the estimates stopped
    last_stop = -math.inf  # when the last stop was sent
    last_taken = math.inf  # when the last estimate was turned into a command (none yet)
    # the last estimate's command was a move: the watchdog owes a stop once the estimates go
    # stale, set point or not (a failed estimate's recover() clears the set point, and the
    # last move then stood for good when the estimates stopped: fuzzy-controller review)
    moving = False
    camera_clock = CameraClock() if args.clock == "camera" else None
    clock = time.time if camera_clock is None else camera_clock.now
    xc0: float | None = None  # xc of the track's first estimate
    used = NO_ESTIMATE  # (seq, stamp_ns) of the last estimate turned into a command
    last = NO_ESTIMATE  # (seq, stamp_ns) of the last estimate not refused for its stamp

    def width_of(est: Estimate) -> float:
        """The width that makes the centring error half-image-widths: --image-width where
        given, else the estimate's frame's. Fixed at 256 px, a 768 px camera's error read 3
        times too large, and the command swung +-0.2 m/s 19 times in a 20 s run (a limit
        cycle; none with the width set)."""
        if args.image_width is not None:
            return float(args.image_width)
        return DEFAULT_WIDTH if est.width is None else float(est.width)

    def send(stamp_ns: int, vx: float, vy: float, wz: float, stale: bool) -> None:
        nonlocal seq
        node.publish(node.keys.cmd_vel, encode_cmd_vel(seq=seq, stamp_ns=stamp_ns, vx=vx, vy=vy,
                                                       wz=wz, stale=stale), reliable=True)
        seq += 1

    held_since: float | None = None  # when the robot began to be held stopped (monotonic)

    def hold(mono: float, why: str) -> None:
        """The robot is held stopped from ``mono`` on: said once (the log's warning and the
        status's ``extra.held_since``) until a command moves it again (:func:`released`)."""
        nonlocal held_since
        if held_since is None:
            # an operator saw a healthy status while the robot was held for minutes
            held_since = mono
            node.status.extra["held_since"] = round(time.time(), 3)
            log.warning("%s: holding the robot stopped until estimates that can be trusted "
                        "come again", why)

    def watchdog() -> None:
        """Repeat the stop while the estimates are stale (none for a while, or too old)."""
        nonlocal last_stop, held_since
        mono = time.monotonic()
        silent = mono - last_taken > ctrl.config.stale_after_s
        if mono - last_stop >= STALE_REPEAT_S and (
                (ctrl.x_ref is not None and (ctrl.command_at(clock()).stale or silent))
                or (moving and silent)):
            # stamped on the host's clock whatever --clock says: on the camera's, a stop
            # stamped after a lockstep simulator's next frame would pass for that frame's answer
            send(time.time_ns(), 0.0, 0.0, 0.0, True)
            last_stop = mono
            extra = node.status.extra
            extra["watchdog_stops"] = extra.get("watchdog_stops", 0) + 1
            hold(mono, f"no fresh estimate for {max(mono - last_taken, 0.0):.2f} s "
                       f"(--stale-after {ctrl.config.stale_after_s:g} s; a stop every "
                       f"{STALE_REPEAT_S:g} s)" if last_taken < math.inf
                 else "no estimate yet")

    def released(cmd_stale: bool) -> None:
        """A command from a fresh estimate: the watchdog's hold, if any, is over (said)."""
        nonlocal held_since
        if held_since is not None and not cmd_stale:
            log.info("estimates fresh again after %.1f s held: driving",
                     time.monotonic() - held_since)
            held_since = None
            node.status.extra.pop("held_since", None)

    def on_estimate(payload: bytes) -> None:
        nonlocal last_stop, last_taken, xc0, used, last, late_in_a_row, moving
        t0 = time.perf_counter()
        now = clock()
        est = decode_or_reject(Estimate, payload, node, log)
        if est is None:
            return
        if (est.seq, est.stamp_ns) == used:  # published again: its command has been sent
            node.status.extra["repeated"] = node.status.extra.get("repeated", 0) + 1
            return
        if came_late(est, last):  # an old estimate after a newer one: no command of its own
            late = node.status.extra["came_late"] = \
                node.status.extra.get("came_late", 0) + 1
            if node.status.say("came late", REJECTED_LOG_S) is not None:
                log.warning("estimate seq %d (stamped %.3g s before seq %d) came after it: "
                            "ignored (%d in all)", est.seq, (last[1] - est.stamp_ns) * 1e-9,
                            last[0], late)
            return
        # The old track's set point and time go with it: a lockstep simulator's clock, ahead
        # of the host's, starts again from the host's time, below the old track's stamps.
        new_track = starts_track(est, last)
        stepped = not new_track and est.seq > last[0] and est.stamp_ns <= last[1]
        if stepped:
            # a later frame stamped before the one before it: the camera's clock was set
            # back (a step of its wall clock). Every estimate was refused as out of order
            # until the clock had caught up (20 s for a 20 s step), the robot not stopped.
            # The controller's timing starts again from this one; the set point stays.
            steps = node.status.extra["clock_steps"] = \
                node.status.extra.get("clock_steps", 0) + 1
            unsaid = node.status.say("clock step", REJECTED_LOG_S)  # 30 lines in 2 s, else
            if unsaid is not None:
                log.warning("estimate seq %d is stamped %.3g s before seq %d: the camera's "
                            "clock was set back; the controller's timing starts again from "
                            "it (%d in all)", est.seq, (last[1] - est.stamp_ns) * 1e-9,
                            last[0], steps)
            ctrl.restart_timing()
        if camera_clock is not None:
            camera_clock.arrived(est.stamp_ns * 1e-9, restart=new_track or stepped)
            now = camera_clock.now()
        ahead = est.stamp_ns * 1e-9 - now
        if ahead > MAX_AHEAD_S:
            reject(node, log, Estimate.KEY, f"stamp_ns {est.stamp_ns} is {ahead:.3g} s ahead "
                   f"of this host's clock (allowed: {MAX_AHEAD_S:g} s): clocks out of step, "
                   "or a bad stamp")
            return
        last = (est.seq, est.stamp_ns)
        if new_track or xc0 is None:  # new features, so a new set point
            ctrl.reset()
            # from the track's first valid estimate: an invalid one's xc is no target's
            xc0 = est.xc if est.valid else None
        # the centroid followed through the robust motion of the matched features, not the
        # raw xc, which jumps whenever features are lost or re-detected (Table 1b); an
        # invalid estimate stops the robot, and so does one that says it is valid with fewer
        # than MIN_VALID_NPI features (the CONTRACT rules it out; a peer's valid: true, npi: 0
        # moved the robot of a controller run with --min-npi 0)
        try:
            cmd = ctrl.update((est.xc if xc0 is None else xc0) + est.dx, est.scale,
                              est.stamp_ns * 1e-9, width_of(est), npi=est.npi,
                              valid=est.valid and est.npi >= MIN_VALID_NPI)
        except ValueError as e:  # out of order or a duplicate: the input's fault, not ours
            reject(node, log, Estimate.KEY, e)
            return
        untrusted = cmd.stale  # the controller's own verdict: a stop for an untrusted estimate
        if not cmd.stale and (late := ctrl.command_at(now)).stale:
            # older than --stale-after on arrival (a camera clock behind this host's, a
            # pipeline slower than the bound): the watchdog's stop, not a move on old news,
            # which it then stopped 0.1 s later, stop and go from data seconds old
            cmd = late
            node.status.extra["late"] = node.status.extra.get("late", 0) + 1
            late_in_a_row += 1
            if late_in_a_row == LATE_SAID_AFTER:
                log.warning("the last %d estimates were all older than --stale-after (%g s) "
                            "when they came (this one %.1f ms): each is answered with a stop. "
                            "The pipeline's latency, or the camera's clock against this "
                            "host's, exceeds it", LATE_SAID_AFTER, ctrl.config.stale_after_s,
                            (now - est.stamp_ns * 1e-9) * 1e3)
        else:
            late_in_a_row = 0
        if cmd is STOP or cmd.stale:
            last_stop = time.monotonic()
            if untrusted:
                extra = node.status.extra
                extra["untrusted"] = extra.get("untrusted", 0) + 1
                hold(last_stop, f"estimate seq {est.seq} cannot be trusted (valid "
                                f"{str(est.valid).lower()}, npi {est.npi}; --min-npi "
                                f"{ctrl.config.min_npi})")
            else:
                hold(last_stop, f"estimate seq {est.seq} is older than --stale-after "
                                f"({ctrl.config.stale_after_s:g} s) when it came")
        last_taken = time.monotonic()
        used = (est.seq, est.stamp_ns)
        send(est.stamp_ns, cmd.vx, cmd.vy, cmd.wz, cmd.stale)
        released(cmd.stale)
        moving = not cmd.stale and (cmd.vx, cmd.vy, cmd.wz) != (0.0, 0.0, 0.0)
        node.status.observe_ms((time.perf_counter() - t0) * 1e3)

    def recover() -> None:
        # an estimate that failed half-way: a new set point from the next one
        nonlocal xc0
        ctrl.reset()
        xc0 = None

    ready(node)
    dispatch(node, {node.keys.estimate: on_estimate}, log, timeout=STALE_REPEAT_S / 2,
             tick=watchdog, recover=recover)
    if seq > 0:
        # stopped (SIGTERM, Ctrl-C, the launcher's stop): the last word is a stop, not the
        # last move, which a base without a timeout of its own went on with (a clean stop of
        # vistrack up ended the controller 0.1 s after the camera, before its watchdog's 0.3 s)
        send(time.time_ns(), 0.0, 0.0, 0.0, True)
        log.info("stopping: sent a stop command (stale)")


def main(args: argparse.Namespace) -> int:
    return serve("fuzzy_controller", args, loop)
