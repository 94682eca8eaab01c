"""Where vistrack's processes listen unless told otherwise: on loopback only (issue 18).

The Zenoh config each service and tool builds from its default flags, the services' flags as
``vistrack up`` gives them, and the embedded router's, read for the mode the session runs in:
no endpoint beyond loopback. What a deployment names (``-l``, a config file's endpoints, the
deploy/multi-host files) is kept as given. No session is opened here; the sockets the real
processes open are checked by tests/service/test_listen.py and, across network namespaces, by
tests/integration/test_listen_netns.py.
"""

from __future__ import annotations

import ipaddress
import json
import re
from pathlib import Path

import pytest
import zenoh

from vistrack.common.bus import config_from_args
from vistrack.services.cli import build_parser
from vistrack.services.launch.launchfile import default_launch
from vistrack.services.launch.router import listen_endpoints, router_config
from vistrack.services.launch.supervisor import Launcher
from vistrack.services.launch.up import launch_from_args

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
SERVICES = ("camera", "preprocessing", "motion-estimation", "auto-tuner", "fuzzy-controller")
# each tool with the positional arguments it requires
TOOLS = {"echo": ["motion/estimate"], "hz": ["motion/estimate"], "status": [],
         "params": ["get"], "record": ["run.vtr"], "replay": ["run.vtr"]}
COMMANDS = {**{name: [] for name in SERVICES}, **TOOLS}


def session_listens_on(conf: zenoh.Config) -> list[str]:
    """The listen endpoints a session opened with ``conf`` uses: Zenoh's ``listen/endpoints``,
    a list or one list per mode, for the config's mode (peer when unset)."""
    mode = json.loads(conf.get_json("mode")) or "peer"
    value = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(value, dict):
        value = value.get(mode) or []
    return [str(e) for e in value]


def is_loopback(endpoint: str) -> bool:
    """Whether ``endpoint`` (``proto/host:port``, options after ? or #) is on a loopback
    address; a name such as ``localhost`` does not count: it could resolve elsewhere."""
    address = re.split(r"[?#]", endpoint.partition("/")[2], maxsplit=1)[0]
    host = address.rsplit(":", 1)[0].strip("[]")
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def config_of(command: str, *flags: str) -> zenoh.Config:
    args = build_parser(command).parse_args([command, *COMMANDS[command], *flags])
    return config_from_args(args)


def test_the_loopback_check_itself():
    assert is_loopback("tcp/127.0.0.1:0") and is_loopback("tcp/[::1]:7447")
    assert is_loopback("tcp/127.0.0.1:7447#iface=lo")
    for endpoint in ("tcp/[::]:0", "tcp/0.0.0.0:7447", "tcp/192.168.1.10:7447",
                     "tls/0.0.0.0:7447", "tcp/localhost:0", "udp/224.0.0.224:7446"):
        assert not is_loopback(endpoint), endpoint


@pytest.mark.parametrize("command", list(COMMANDS))
def test_default_flags_listen_on_loopback_only(command):
    endpoints = session_listens_on(config_of(command))
    assert endpoints, f"vistrack {command}: a peer listens, so local peers connect directly"
    assert all(is_loopback(e) for e in endpoints), (command, endpoints)


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("mode", ["peer", "router", "client"])
def test_every_mode_listens_on_loopback_only(command, mode):
    endpoints = session_listens_on(config_of(command, "-m", mode,
                                             "-e", "tcp/127.0.0.1:7447"))
    assert all(is_loopback(e) for e in endpoints), (command, mode, endpoints)
    if mode == "client":
        assert endpoints == []  # a client only connects


def test_services_as_vistrack_up_starts_them_listen_on_loopback_only():
    launch = default_launch()
    launcher = Launcher(launch)  # not started: only the command lines it would run
    for spec in launch.services:
        argv = launcher._command(spec)[3:]  # after: python -m vistrack.services.cli
        assert argv[0] == spec.cli_name
        conf = config_from_args(build_parser(argv[0]).parse_args(argv))
        endpoints = session_listens_on(conf)
        assert endpoints and all(is_loopback(e) for e in endpoints), (argv, endpoints)


def test_embedded_and_standalone_router_listen_on_loopback_only(tmp_path):
    up = build_parser("up").parse_args(["up"])
    assert all(is_loopback(e) for e in launch_from_args(up).listen)
    assert all(is_loopback(e) for e in listen_endpoints(router_config(None)))
    # a config file that names no listen endpoints does not open Zenoh's default either
    path = tmp_path / "router.json5"
    path.write_text('{ mode: "router", scouting: { multicast: { enabled: false } } }')
    up = build_parser("up").parse_args(["up", "-c", str(path)])
    assert launch_from_args(up).listen == ("tcp/127.0.0.1:7447",)
    assert listen_endpoints(router_config(None, str(path))) == ["tcp/127.0.0.1:7447"]


def test_a_config_file_without_endpoints_gets_the_loopback_default(tmp_path):
    path = tmp_path / "peer.json5"
    path.write_text('{ connect: { endpoints: ["tcp/127.0.0.1:7447"] } }')
    endpoints = session_listens_on(config_of("echo", "-c", str(path)))
    assert endpoints == ["tcp/127.0.0.1:0"]


# -- what a deployment says is kept -------------------------------------------------------

def test_listen_flag_is_kept_as_given():
    conf = config_of("camera", "-l", "tcp/0.0.0.0:7450", "-l", "tcp/[::]:7451")
    assert session_listens_on(conf) == ["tcp/0.0.0.0:7450", "tcp/[::]:7451"]
    up = build_parser("up").parse_args(["up", "-l", "tcp/0.0.0.0:7447"])
    assert launch_from_args(up).listen == ("tcp/0.0.0.0:7447",)


@pytest.mark.parametrize(("text", "expected"), [
    ('{ listen: { endpoints: ["tcp/0.0.0.0:7449"] } }', ["tcp/0.0.0.0:7449"]),
    ('{ listen: { endpoints: { peer: ["tcp/[::]:0"] } } }', ["tcp/[::]:0"]),
    ('{ listen: { endpoints: [] } }', []),  # told to listen nowhere
])
def test_a_config_files_endpoints_are_kept(tmp_path, text, expected):
    path = tmp_path / "peer.json5"
    path.write_text(text)
    assert session_listens_on(config_of("fuzzy-controller", "-c", str(path))) == expected


@pytest.mark.parametrize(("name", "expected"), [
    ("router.json5", ["tls/0.0.0.0:7447"]),  # the central router: the network, over mTLS
    ("robot.json5", ["tcp/127.0.0.1:7447"]),
    ("base.json5", ["tcp/127.0.0.1:7448"]),
    ("operator.json5", []),  # a client
])
def test_multi_host_configs_listen_where_they_say(name, expected):
    conf = config_of("status", "-c", str(DEPLOY / "multi-host" / name))
    assert session_listens_on(conf) == expected


@pytest.mark.parametrize(("flags", "said"), [
    ([], "the local network (multicast scouting; give -e ENDPOINT for a router)"),
    (["--no-multicast-scouting"], "no endpoint (--no-multicast-scouting without -e, -l or -c: "
                                  "nothing can be reached; give -e ENDPOINT for a router)"),
    (["--no-multicast-scouting", "-e", "tcp/127.0.0.1:7447"], "tcp/127.0.0.1:7447"),
])
def test_a_tool_says_where_it_looks(flags, said):
    """A tool run with --no-multicast-scouting and no endpoint can reach nothing, but said it
    was scouting the local network (a hunt of the README against the tools)."""
    from vistrack.services.tools.shared import where

    assert where(build_parser().parse_args(["echo", "motion/estimate", *flags])) == said
