"""Every Zenoh key expression of the system, built from the robot id.

All keys live under ``vistrack/<robot>/`` so several robots share one Zenoh network
(ARCHITECTURE.md, "CONTRACT: keys and messages"):

==================  ==============================  ==========================
attribute           key suffix                      message (common.messages)
==================  ==============================  ==========================
``frame``           ``camera/frame``                ``Frame``
``pre_frame``       ``preprocessing/frame``         ``PreFrame``
``estimate``        ``motion/estimate``             ``Estimate``
``params``          ``tuner/params``                ``Params``
``report``          ``tuner/report``                ``Report``
``cmd_vel``         ``control/cmd_vel``             ``CmdVel``
``demand``          ``motion/demand``               ``Demand``
``pose``            ``sim/pose``                    ``Pose``
``pre_done``        ``preprocessing/done``          ``PreDone``
==================  ==============================  ==========================

Each service also declares the liveliness token ``vistrack/<robot>/alive/<service>`` and answers
queries on ``vistrack/<robot>/<service>/status``; a ``vistrack up`` that joins a router declares
``vistrack/<robot>/launcher/<zid>``.
"""

from __future__ import annotations

import re

PREFIX = "vistrack"

#: Service names as they appear in keys (liveliness tokens, status queryables, launch files).
SERVICES = ("camera", "preprocessing", "motion_estimation", "auto_tuner", "fuzzy_controller")
#: Services a launch file may add to those: not part of the default launch.
OPTIONAL_SERVICES = ("ros2",)
#: Every service name a launch file accepts.
LAUNCHABLE = (*SERVICES, *OPTIONAL_SERVICES)

#: Attribute name of :class:`Keys` -> contract key suffix under ``vistrack/<robot>/``.
CONTRACT_SUFFIXES: dict[str, str] = {
    "frame": "camera/frame",
    "pre_frame": "preprocessing/frame",
    "estimate": "motion/estimate",
    "params": "tuner/params",
    "report": "tuner/report",
    "cmd_vel": "control/cmd_vel",
    "demand": "motion/demand",
    "pose": "sim/pose",
    "pre_done": "preprocessing/done",
}

# One key chunk: robot ids and service names must not contain '/', wildcards ('*'), or the
# characters Zenoh reserves ('$', '#', '?'), so a conservative alphabet is enforced.
_ID_RE = re.compile(r"[A-Za-z0-9_-]+")
# A key chunk in a user-given key (``vistrack echo KEY``): also allows '.', '*' and '**'.
_CHUNK_RE = re.compile(r"(\*\*|\*|[A-Za-z0-9_.-]+)")


def validate_robot_id(robot: object) -> str:
    """Return ``robot`` if it is a valid robot id, else raise ``ValueError`` naming it.

    A robot id is one key chunk: non-empty, made of ``A-Z a-z 0-9 _ -`` only.
    """
    return _validate_id("robot id", robot)


def validate_service_name(service: object) -> str:
    """Return ``service`` if it can be used as a key chunk (same alphabet as robot ids).

    Services use the names in :data:`SERVICES`; tools and tests may use other names.
    """
    return _validate_id("service name", service)


def _validate_id(what: str, value: object) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{what} {value!r} must be a string")
    if not _ID_RE.fullmatch(value):
        raise ValueError(f"{what} {value!r} is not allowed: use a non-empty string of "
                         "letters, digits, '_' and '-' only")
    return value


class Keys:
    """The key expressions of one robot.

    Parameters
    ----------
    robot : robot id (see :func:`validate_robot_id`), default ``"robot"``.

    Attributes
    ----------
    robot : the robot id.
    root : ``"vistrack/<robot>"``.
    frame, pre_frame, estimate, params, report, cmd_vel, demand, pose, pre_done : the contract
        keys (see the module docstring).
    """

    __slots__ = ("robot", "root", *CONTRACT_SUFFIXES)

    def __init__(self, robot: str = "robot") -> None:
        self.robot = validate_robot_id(robot)
        self.root = f"{PREFIX}/{robot}"
        for attr, suffix in CONTRACT_SUFFIXES.items():
            setattr(self, attr, f"{self.root}/{suffix}")

    # explicit attribute annotations for readers and type checkers (set in __init__)
    frame: str
    pre_frame: str
    estimate: str
    params: str
    report: str
    cmd_vel: str
    demand: str
    pose: str
    pre_done: str

    def alive(self, service: str) -> str:
        """Liveliness token key of ``service``: ``vistrack/<robot>/alive/<service>``."""
        return f"{self.root}/alive/{validate_service_name(service)}"

    def status(self, service: str) -> str:
        """Status queryable key of ``service``: ``vistrack/<robot>/<service>/status``."""
        return f"{self.root}/{validate_service_name(service)}/status"

    def alive_any(self) -> str:
        """Key expression matching every liveliness token of this robot."""
        return f"{self.root}/alive/*"

    def launcher(self, zid: str) -> str:
        """Liveliness token key of the ``vistrack up`` that runs this robot's services
        through a router it joins, by its Zenoh session id: ``vistrack/<robot>/launcher/<zid>``
        (two launchers of one robot id started at once see each other by it, before either
        has a service alive)."""
        return f"{self.root}/launcher/{validate_service_name(zid)}"

    def launcher_any(self) -> str:
        """Key expression matching every launcher token of this robot."""
        return f"{self.root}/launcher/*"

    def status_any(self) -> str:
        """Key expression matching every status queryable of this robot."""
        return f"{self.root}/*/status"

    def resolve(self, key: str) -> str:
        """Turn a short name into a full key of this robot.

        Accepts a contract suffix (``"motion/estimate"``), an attribute name (``"estimate"``),
        any other relative key (``"camera/status"``, ``"**"``), or a full key starting with
        ``"vistrack/"``, which is returned unchanged (it may name another robot).

        Raises
        ------
        ValueError
            If ``key`` is empty or not a well-formed key expression (empty chunks, leading or
            trailing '/', characters outside ``A-Z a-z 0-9 _ - .`` besides ``*`` / ``**``).
        """
        if not isinstance(key, str) or not key:
            raise ValueError(f"key {key!r} must be a non-empty string")
        if key in CONTRACT_SUFFIXES:
            return getattr(self, key)
        chunks = key.split("/")
        bad = [c for c in chunks if not _CHUNK_RE.fullmatch(c)]
        if bad:
            raise ValueError(f"key {key!r} is not a valid key expression: chunk {bad[0]!r} "
                             "(chunks are non-empty, letters, digits, '_', '-', '.', or * / **)")
        if chunks[0] == PREFIX:
            return key
        return f"{self.root}/{key}"

    def __repr__(self) -> str:
        return f"Keys(robot={self.robot!r})"


def key_suffix(key: str) -> str:
    """The part of a full key after ``vistrack/<robot>/`` (any robot); other strings unchanged.

    ``key_suffix("vistrack/r1/motion/estimate") == "motion/estimate"``.
    """
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[0] == PREFIX:
        return parts[2]
    return key
