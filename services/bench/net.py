"""bench_net: what crossing machines costs, measured on real network namespaces.

``python -m vistrack.services.bench.net [--seconds S] [--rounds N] [--json]`` (as root, for the
namespaces; without root only the loopback rows are measured) prints one table:

* latency: the round trip of a payload between two processes (a pinger and an echo, plain
  zenoh, no project code), halved; for a camera frame (256x256 = 64 KiB) and an estimate-sized
  payload (2 KiB); median and p99 over N round trips;
* throughput: a source publishing 64 KiB frames as fast as reliable delivery allows
  (congestion control BLOCK, so nothing is dropped and the slowest link sets the pace) into a
  sink for S seconds: frames per second and MB/s at the sink.

over these paths:

====================  ==========================================================================
loopback p2p shm      two peers on 127.0.0.1, connected directly, Zenoh's shared memory on (its
                      default: large payloads go through /dev/shm, only their handles through
                      TCP); every other path has it off, so bytes cross the links as between
                      machines
loopback p2p          two peers on 127.0.0.1, connected directly
loopback router       both clients of a router on 127.0.0.1 (``vistrack up`` on one machine)
netns router tcp      pinger on the robot namespace, echo on the base namespace, both clients of a
                      router in a third namespace (veth pairs on a bridge, 10.77.0.0/24), plain TCP
netns router tls      the same over mutual TLS (deploy/multi-host/router.json5's TLS settings)
netns deployment      the production path of deploy/multi-host: robot client -> the robot's
                      embedded router (loopback) -> mTLS -> the central router -> mTLS -> the
                      base's embedded router -> base client
====================  ==========================================================================

The certificates are made with :mod:`.certs` in a temporary directory; the namespaces are
created for the run and deleted at the end, also on failure (Ctrl-C included). Each process is
``python -m vistrack.services.bench.net --role ROLE CONFIG.json5 ...`` (run under
``ip netns exec NS`` for the namespaces). Absolute figures depend on the machine and its load;
the ratios between rows of one run are what to read.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

FRAME = 256 * 256
ESTIMATE = 2048
SUBNET = "10.77.0"
ROUTER_IP, ROBOT_IP, BASE_IP = f"{SUBNET}.1", f"{SUBNET}.2", f"{SUBNET}.3"
READY_S = 30.0
PING, PONG, FRAMES = "bench/ping", "bench/pong", "bench/frames"


# -- the roles, one per process -----------------------------------------------------------

def _open(config: str) -> Any:
    import zenoh

    return zenoh.open(zenoh.Config.from_file(config))


def _wait_stdin() -> None:
    sys.stdin.read()  # the orchestrator closes our stdin to stop us


def role_router(config: str) -> None:
    with _open(config):
        print("ready", flush=True)
        _wait_stdin()


def role_echo(config: str) -> None:
    with _open(config) as s:
        pub = s.declare_publisher(PONG)
        sub = s.declare_subscriber(PING, lambda smp: pub.put(smp.payload))
        print("ready", flush=True)
        _wait_stdin()
        sub.undeclare()


def role_ping(config: str, sizes: list[int], rounds: int) -> None:
    """Round trips through the echo for each payload size; prints {"SIZE": [rtt_s, ...]}."""
    import zenoh

    got = threading.Event()
    out: dict[str, list[float]] = {}
    with _open(config) as s:
        sub = s.declare_subscriber(PONG, lambda smp: got.set())
        pub = s.declare_publisher(PING, congestion_control=zenoh.CongestionControl.BLOCK)

        def once(payload: bytes, timeout: float) -> float | None:
            got.clear()
            t0 = time.perf_counter()
            pub.put(payload)
            return time.perf_counter() - t0 if got.wait(timeout) else None

        deadline = time.monotonic() + READY_S
        while once(b"x", 0.2) is None:  # until the echo answers: routes are in place
            if time.monotonic() > deadline:
                raise SystemExit("bench_net ping: the echo never answered")
        for size in sizes:
            payload = os.urandom(size)
            for _ in range(20):  # warm the path (allocations, TCP windows)
                once(payload, 2.0)
            rtts = [once(payload, 2.0) for _ in range(rounds)]
            if None in rtts:
                raise SystemExit("bench_net ping: no answer within 2 s")
            out[str(size)] = [t for t in rtts if t is not None]
        sub.undeclare()
    print(json.dumps(out), flush=True)


def role_sink(config: str, seconds: float) -> None:
    """Counts frames for ``seconds`` after the first one; prints {"frames", "bytes", "s"}."""
    lock = threading.Lock()
    first = threading.Event()
    count = [0, 0, 0.0]

    def on(sample: Any) -> None:
        n = len(sample.payload)
        with lock:
            if not first.is_set():
                count[2] = time.perf_counter()
                first.set()
                return
            count[0] += 1
            count[1] += n

    with _open(config) as s:
        sub = s.declare_subscriber(FRAMES, on)
        print("ready", flush=True)
        if not first.wait(READY_S):
            raise SystemExit("bench_net sink: no frame arrived")
        time.sleep(seconds)  # the measurement window
        with lock:
            frames, nbytes, t0 = count
            elapsed = time.perf_counter() - t0
        sub.undeclare()
    print(json.dumps({"frames": frames, "bytes": nbytes, "s": elapsed}), flush=True)


def role_source(config: str, size: int) -> None:
    """Publishes ``size``-byte frames, BLOCK congestion control, until stdin closes."""
    import zenoh

    stop = threading.Event()

    def wait_then_stop() -> None:
        _wait_stdin()
        stop.set()

    threading.Thread(target=wait_then_stop, daemon=True).start()
    with _open(config) as s:
        pub = s.declare_publisher(FRAMES, congestion_control=zenoh.CongestionControl.BLOCK)
        payload = os.urandom(size)
        print("ready", flush=True)
        while not stop.is_set():
            pub.put(payload)


# -- configurations ---------------------------------------------------------------------------

def _tls(certs: Path, name: str) -> dict[str, Any]:
    """The TLS block of deploy/multi-host for the certificate ``name``."""
    key, cert = str(certs / f"{name}.key"), str(certs / f"{name}.pem")
    return {"root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
            "listen_private_key": key, "listen_certificate": cert,
            "connect_private_key": key, "connect_certificate": cert,
            "verify_name_on_connect": True}


def _config(path: Path, mode: str, *, listen: list[str] | None = None,
            connect: list[str] | None = None, tls: dict[str, Any] | None = None,
            shm: bool = False) -> str:
    """A zenoh config file. ``shm`` False turns off Zenoh's shared-memory transport, which
    otherwise carries every payload over 3 KiB through /dev/shm between processes of one host
    (namespaces included), so the bytes would never cross the veth links: off, the paths
    behave as between machines."""
    conf: dict[str, Any] = {"mode": mode, "listen": {"endpoints": listen or []},
                            "connect": {"endpoints": connect or []},
                            "scouting": {"multicast": {"enabled": False},
                                         "gossip": {"enabled": mode == "peer"}},
                            "transport": {"shared_memory": {"enabled": shm}}}
    if mode == "router" and connect:
        conf["connect"].update(exit_on_failure=False, timeout_ms=-1)
    if tls is not None:
        conf["transport"]["link"] = {"tls": tls}
    path.write_text(json.dumps(conf, indent=1))
    return str(path)


# -- processes and namespaces -------------------------------------------------------------------

class _Proc:
    def __init__(self, ns: str | None, role: str, *args: str) -> None:
        cmd = [sys.executable, "-m", "vistrack.services.bench.net", "--role", role, *args]
        if ns is not None:
            cmd = ["ip", "netns", "exec", ns, *cmd]
        # stderr to a file: a pipe nobody reads could fill up and block the process
        self.err = tempfile.TemporaryFile("w+")
        self.p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=self.err, text=True)
        self.role = role

    def _failure(self, what: str) -> RuntimeError:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()
        self.err.seek(0)
        text = self.err.read()[-800:]
        self.stop()
        return RuntimeError(f"bench_net {self.role}: {what}: {text}")

    def ready(self) -> _Proc:
        line = _readline(self.p, READY_S)
        if line.strip() != "ready":
            raise self._failure(f"not ready ({line.strip() or 'no output'})")
        return self

    def result(self, timeout: float) -> dict[str, Any]:
        line = _readline(self.p, timeout)
        try:
            return json.loads(line)
        except json.JSONDecodeError:
            raise self._failure(f"no result ({line.strip() or 'no output'})") from None

    def stop(self) -> None:
        if self.p.poll() is None:
            try:
                assert self.p.stdin is not None
                self.p.stdin.close()
                self.p.wait(5)
            except (subprocess.TimeoutExpired, BrokenPipeError):
                self.p.kill()
                self.p.wait()
        for f in (self.p.stdin, self.p.stdout):
            if f is not None and not f.closed:
                f.close()
        self.err.close()


def _readline(p: subprocess.Popen[str], timeout: float) -> str:
    assert p.stdout is not None
    stdout = p.stdout
    out: list[str] = []
    t = threading.Thread(target=lambda: out.append(stdout.readline()), daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        raise RuntimeError(f"no output within {timeout} s")
    return out[0] if out else ""


@contextmanager
def _running(*procs: _Proc) -> Iterator[None]:
    try:
        for p in procs:
            p.ready()
        yield
    finally:
        for p in reversed(procs):
            p.stop()


def _ip(*args: str) -> None:
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if proc.returncode:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")


@contextmanager
def lan() -> Iterator[tuple[str, str, str]]:
    """Router, robot and base namespaces on a bridge; deleted on exit with what runs in them."""
    tag = f"vb{os.getpid() % 100000}{uuid.uuid4().hex[:4]}"
    names = [f"{tag}-{h}" for h in ("router", "robot", "base")]
    made: list[str] = []
    try:
        for ns in names:
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        router = names[0]
        _ip("-n", router, "link", "add", "br0", "type", "bridge")
        _ip("-n", router, "addr", "add", f"{ROUTER_IP}/24", "dev", "br0")
        _ip("-n", router, "link", "set", "br0", "up")
        for ns, addr, port in ((names[1], ROBOT_IP, "p-robot"), (names[2], BASE_IP, "p-base")):
            _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", port,
                "netns", router)
            _ip("-n", router, "link", "set", port, "master", "br0", "up")
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
        yield names[0], names[1], names[2]
    finally:
        for ns in reversed(made):
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                                  text=True).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# -- the paths ------------------------------------------------------------------------------

class NetPath:
    """One path: where the routers, pinger/source and echo/sink run, and their configs."""

    def __init__(self, name: str, routers: list[tuple[str | None, str]],
                 a: tuple[str | None, str], b: tuple[str | None, str]) -> None:
        self.name, self.routers, self.a, self.b = name, routers, a, b

    @contextmanager
    def up(self) -> Iterator[None]:
        with ExitStack() as stack:
            for ns, conf in self.routers:
                stack.enter_context(_running(_Proc(ns, "router", conf)))
            yield

    def latency(self, sizes: list[int], rounds: int) -> dict[int, list[float]]:
        """One-way latencies (s) for each payload size."""
        with self.up():
            echo = _Proc(self.b[0], "echo", self.b[1])
            with _running(echo):
                ping = _Proc(self.a[0], "ping", self.a[1], "--size",
                             ",".join(str(n) for n in sizes), "--rounds", str(rounds))
                try:
                    got = ping.result(READY_S + len(sizes) * rounds * 2.0)
                finally:
                    ping.stop()
        return {int(size): [t / 2 for t in rtts] for size, rtts in got.items()}

    def throughput(self, seconds: float) -> dict[str, float]:
        with self.up():
            sink = _Proc(self.b[0], "sink", self.b[1], "--seconds", str(seconds))
            sink.ready()
            try:
                source = _Proc(self.a[0], "source", self.a[1], "--size", str(FRAME))
                with _running(source):
                    got = sink.result(READY_S + seconds + 10)
            finally:
                sink.stop()
        return {"fps": got["frames"] / got["s"], "mb_s": got["bytes"] / got["s"] / 1e6}


def _paths(tmp: Path, certs: Path, ns: tuple[str, str, str] | None) -> list[NetPath]:
    port = _free_port()
    lo = f"tcp/127.0.0.1:{port}"
    paths = [
        NetPath("loopback p2p shm", [],
                (None, _config(tmp / "shm-a.json5", "peer", connect=[lo], shm=True)),
                (None, _config(tmp / "shm-b.json5", "peer", listen=[lo], shm=True))),
        NetPath("loopback p2p", [],
              (None, _config(tmp / "p2p-a.json5", "peer", connect=[lo])),
              (None, _config(tmp / "p2p-b.json5", "peer", listen=[lo]))),
        NetPath("loopback router", [(None, _config(tmp / "lr.json5", "router", listen=[lo]))],
              (None, _config(tmp / "lr-a.json5", "client", connect=[lo])),
              (None, _config(tmp / "lr-b.json5", "client", connect=[lo]))),
    ]
    if ns is None:
        return paths
    r, robot, base = ns
    tcp, tls = f"tcp/{ROUTER_IP}:7447", f"tls/{ROUTER_IP}:7447"
    paths += [
        NetPath("netns router tcp",
              [(r, _config(tmp / "rt.json5", "router", listen=["tcp/0.0.0.0:7447"]))],
              (robot, _config(tmp / "rt-a.json5", "client", connect=[tcp])),
              (base, _config(tmp / "rt-b.json5", "client", connect=[tcp]))),
        NetPath("netns router tls",
              [(r, _config(tmp / "rs.json5", "router", listen=["tls/0.0.0.0:7447"],
                           tls=_tls(certs, "vistrack-router")))],
              (robot, _config(tmp / "rs-a.json5", "client", connect=[tls],
                              tls=_tls(certs, "vistrack-robot"))),
              (base, _config(tmp / "rs-b.json5", "client", connect=[tls],
                             tls=_tls(certs, "vistrack-base")))),
        NetPath("netns deployment",
              [(r, _config(tmp / "d.json5", "router", listen=["tls/0.0.0.0:7447"],
                           tls=_tls(certs, "vistrack-router"))),
               (robot, _config(tmp / "d-robot.json5", "router", listen=["tcp/127.0.0.1:7447"],
                               connect=[tls], tls=_tls(certs, "vistrack-robot"))),
               (base, _config(tmp / "d-base.json5", "router", listen=["tcp/127.0.0.1:7448"],
                              connect=[tls], tls=_tls(certs, "vistrack-base")))],
              (robot, _config(tmp / "d-a.json5", "client", connect=["tcp/127.0.0.1:7447"])),
              (base, _config(tmp / "d-b.json5", "client", connect=["tcp/127.0.0.1:7448"]))),
    ]
    return paths


def _can_make_namespaces() -> str | None:
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "not root"
    if shutil.which("ip") is None:
        return "no ip command (iproute2)"
    return None


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))]


def bench_net(out: Any = sys.stdout, *, seconds: float = 3.0, rounds: int = 300,
              repeat: int = 3, namespaces: bool = True) -> dict[str, float]:
    """Measure every path ``repeat`` times, interleaved (so a burst of load elsewhere on the
    machine hits every path alike), print the table of the medians; return the figures
    (ms, frames/s, MB/s)."""
    from ..launch.certs import issue, make_ca

    why_not = _can_make_namespaces() if namespaces else "--no-netns"
    lat: dict[str, dict[int, list[float]]] = {}
    thr: dict[str, list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="vistrack-bench-net-") as tmp_dir, ExitStack() as st:
        tmp = Path(tmp_dir)
        certs = tmp / "certs"
        make_ca(certs)
        issue(certs, "vistrack-router", [ROUTER_IP])
        for name in ("vistrack-robot", "vistrack-base"):
            issue(certs, name)
        ns = st.enter_context(lan()) if why_not is None else None
        paths = _paths(tmp, certs, ns)
        for _ in range(repeat):
            for path in paths:
                for size, values in path.latency([FRAME, ESTIMATE], rounds).items():
                    lat.setdefault(path.name, {}).setdefault(size, []).extend(values)
                thr.setdefault(path.name, []).append(path.throughput(seconds))
    fig: dict[str, float] = {}
    print(f"# vistrack bench net: one-way latency (round trip / 2; {repeat} x {rounds} round "
          f"trips) and reliable 64 KiB frame throughput (median of {repeat} x {seconds:g} s); "
          f"{os.cpu_count()} CPUs", file=out)
    print(f"{'path':18s} {'64KiB p50':>10s} {'p99':>8s} {'2KiB p50':>9s} {'p99':>8s} "
          f"{'frames/s':>9s} {'MB/s':>7s}", file=out)
    for name, by_size in lat.items():
        key = name.replace(" ", "_")
        fps = sorted(t["fps"] for t in thr[name])[len(thr[name]) // 2]
        fig.update({f"{key}_frame_ms": _pct(by_size[FRAME], 50) * 1e3,
                    f"{key}_frame_p99_ms": _pct(by_size[FRAME], 99) * 1e3,
                    f"{key}_small_ms": _pct(by_size[ESTIMATE], 50) * 1e3,
                    f"{key}_small_p99_ms": _pct(by_size[ESTIMATE], 99) * 1e3,
                    f"{key}_fps": fps, f"{key}_mb_s": fps * FRAME / 1e6})
        print(f"{name:18s} {fig[key + '_frame_ms']:8.3f}ms {fig[key + '_frame_p99_ms']:6.3f}ms "
              f"{fig[key + '_small_ms']:7.3f}ms {fig[key + '_small_p99_ms']:6.3f}ms "
              f"{fps:9.0f} {fig[key + '_mb_s']:7.1f}", file=out)
    if why_not is not None:
        print(f"(namespace paths skipped: {why_not})", file=out)
    else:
        cost = 1 - fig["netns_router_tls_fps"] / fig["netns_router_tcp_fps"]
        fig["tls_throughput_cost"] = cost
        print(f"TLS through the router: {cost * 100:+.0f} % frame throughput cost; one-way "
              f"64 KiB latency {fig['netns_router_tls_frame_ms']:.3f} ms against "
              f"{fig['netns_router_tcp_frame_ms']:.3f} ms over plain TCP", file=out)
    return fig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vistrack.services.bench.net",
                                     description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--role", choices=("router", "echo", "ping", "sink", "source"),
                        help=argparse.SUPPRESS)
    parser.add_argument("config", nargs="?", help=argparse.SUPPRESS)
    parser.add_argument("--size", default=str(FRAME), help=argparse.SUPPRESS)
    parser.add_argument("--rounds", type=int, default=300, help="round trips per latency")
    parser.add_argument("--seconds", type=float, default=3.0, help="throughput window")
    parser.add_argument("--repeat", type=int, default=3, help="measurements of each path")
    parser.add_argument("--no-netns", action="store_true",
                        help="loopback paths only (no root needed)")
    parser.add_argument("--json", action="store_true", help="also print the figures as JSON")
    args = parser.parse_args(argv)
    if args.role is not None:
        role = args.role
        if role == "router":
            role_router(args.config)
        elif role == "echo":
            role_echo(args.config)
        elif role == "ping":
            role_ping(args.config, [int(n) for n in args.size.split(",")], args.rounds)
        elif role == "sink":
            role_sink(args.config, args.seconds)
        else:
            role_source(args.config, int(args.size))
        return 0
    fig = bench_net(seconds=args.seconds, rounds=args.rounds, repeat=args.repeat,
                    namespaces=not args.no_netns)
    if args.json:
        print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())
