"""Hosts as network namespaces, for the tests that need more than one machine.

:class:`Lan` makes namespaces on one LAN (a bridge in the first host's namespace, a veth link
from each other host to it; every address exists inside the namespaces only), and deletes them
at the end, also on failure, after killing what still runs in them. :func:`lan_or_skip` skips,
with the reason, when not root, without iproute2's ``ip``, or where namespaces cannot be
created (an unprivileged container). :class:`NsProc` runs a vistrack command on a host and
keeps its output line by line; :class:`Stream` is ``vistrack echo KEY`` on a host;
:func:`listening_sockets` lists the sockets a host's processes listen on, from /proc (what
``ss -ltunp`` shows inside the namespace).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

STOP_S = 10.0


def cannot_run() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "needs root to create network namespaces (ip netns)"
    if shutil.which("ip") is None:
        return "needs the ip command of iproute2 (apt-get install iproute2)"
    return None


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if check and proc.returncode:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")
    return proc


class Lan:
    """Hosts on one /24 LAN: ``hosts`` maps a host name to its address; the first host holds
    the bridge (its address on ``br0``), every other one is linked to it by a veth pair
    (``eth0`` on its side). ``ns[host]`` is the namespace's name, unique per run."""

    def __init__(self, hosts: dict[str, str]) -> None:
        tag = f"vt{os.getpid() % 100000}{uuid.uuid4().hex[:4]}"
        self.ns = {host: f"{tag}-{host}" for host in hosts}
        self.addr = dict(hosts)
        self.made: list[str] = []

    def build(self) -> None:
        for ns in self.ns.values():
            ip("netns", "add", ns)
            self.made.append(ns)
            ip("-n", ns, "link", "set", "lo", "up")
        first, *others = self.ns
        hub = self.ns[first]
        ip("-n", hub, "link", "add", "br0", "type", "bridge")
        ip("-n", hub, "addr", "add", f"{self.addr[first]}/24", "dev", "br0")
        ip("-n", hub, "link", "set", "br0", "up")
        for host in others:
            ns, port = self.ns[host], f"p-{host}"
            # both ends are created inside the namespaces: nothing appears in the host's
            ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", port,
               "netns", hub)
            ip("-n", hub, "link", "set", port, "master", "br0", "up")
            ip("-n", ns, "addr", "add", f"{self.addr[host]}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")

    def link(self, ns: str, up: bool) -> None:
        ip("-n", ns, "link", "set", "eth0", "up" if up else "down")

    def close(self) -> None:
        for ns in reversed(self.made):
            for pid in ip("netns", "pids", ns, check=False).stdout.split():
                try:  # only what the tests started: it runs in their namespaces
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            ip("netns", "del", ns, check=False)
        self.made.clear()


@contextmanager
def lan_or_skip(lan: Lan) -> Iterator[Lan]:
    """Build ``lan`` (or skip the tests with the reason) and delete it afterwards."""
    reason = cannot_run()
    if reason:
        pytest.skip(reason)
    try:
        lan.build()
    except RuntimeError as e:
        made_any = bool(lan.made)
        lan.close()
        if not made_any and "Operation not permitted" in str(e):
            pytest.skip(f"cannot create network namespaces here: {e}")
        raise
    try:
        yield lan
    finally:
        lan.close()


def cli(ns: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "vistrack.services.cli", *args]


def tool(ns: str, *args: str, timeout: float = 40.0) -> subprocess.CompletedProcess[str]:
    """Run a vistrack tool on a host to completion."""
    return subprocess.run(cli(ns, *args), capture_output=True, text=True, timeout=timeout)


def python(ns: str, code: str, *args: str, timeout: float = 40.0
           ) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", code, *args],
                          capture_output=True, text=True, timeout=timeout)


@dataclass
class Line:
    t: float  # arrival, time.monotonic()
    text: str


class NsProc:
    """A long-running vistrack command on a host; its merged output kept line by line."""

    def __init__(self, ns: str, *args: str) -> None:
        self.args = args
        self.proc = subprocess.Popen(cli(ns, *args), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     text=True, bufsize=1,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[Line] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            with self._cond:
                self.lines.append(Line(time.monotonic(), raw.rstrip("\n")))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    @property
    def output(self) -> str:
        """Everything printed so far."""
        with self._cond:
            return "\n".join(line.text for line in self.lines)

    @property
    def tail(self) -> str:
        with self._cond:
            return "\n".join(line.text for line in self.lines[-40:])

    def wait_line(self, pattern: str, timeout: float) -> str:
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.lines:
                    if regex.search(line.text):
                        return line.text
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self._reader.is_alive()):
                    raise AssertionError(f"{self.args[0]}: no line matching {pattern!r} within "
                                         f"{timeout} s (exit {self.proc.poll()}):\n{self.tail}")
                self._cond.wait(min(left, 0.2))

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(STOP_S)
        self._reader.join(STOP_S)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode


class Stream(NsProc):
    """``vistrack echo KEY`` on a host: the samples it prints, with their arrival times."""

    def __init__(self, ns: str, key: str, endpoint: str) -> None:
        super().__init__(ns, "echo", key, "-e", endpoint, "--no-multicast-scouting")

    def samples(self, since: float = 0.0) -> list[tuple[float, dict[str, Any]]]:
        with self._cond:
            lines = [line for line in self.lines if line.t >= since]
        return [(line.t, json.loads(line.text)) for line in lines if line.text.startswith("{")]

    def wait(self, pred: Callable[[list[dict[str, Any]]], bool], since: float, timeout: float,
             what: str) -> list[dict[str, Any]]:
        """The samples arrived since ``since`` once ``pred`` holds for them."""
        deadline = time.monotonic() + timeout
        while True:
            got = [m for _, m in self.samples(since)]
            if pred(got):
                return got
            if time.monotonic() > deadline:
                raise AssertionError(f"{what}: not within {timeout} s ({len(got)} samples of "
                                     f"{self.args[1]}); last output:\n{self.tail[-2000:]}")
            with self._cond:
                self._cond.wait(0.2)


# -- listening sockets, from /proc ------------------------------------------------------------

@dataclass(frozen=True)
class Socket:
    """A socket a process listens on: a TCP listener, or a UDP socket (which takes datagrams
    from anyone who can reach its address)."""

    proto: str  # "tcp" or "udp"
    address: str  # as an IP literal, IPv6 without brackets
    port: int
    pid: int
    command: str

    @property
    def loopback(self) -> bool:
        return ipaddress.ip_address(self.address).is_loopback

    def __str__(self) -> str:
        host = f"[{self.address}]" if ":" in self.address else self.address
        return f"{self.proto}/{host}:{self.port} ({self.command}, pid {self.pid})"


def _address(hex_addr: str) -> tuple[str, int]:
    """An address of /proc/net/{tcp,udp}[6]: host bytes as 32-bit words in host order."""
    host, port = hex_addr.split(":")
    raw = bytes.fromhex(host)
    words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    family = socket.AF_INET if len(raw) == 4 else socket.AF_INET6
    address = ipaddress.ip_address(socket.inet_ntop(family, words))
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return str(address), int(port, 16)


def listening_sockets(pids: list[int]) -> list[Socket]:
    """The TCP listeners and UDP sockets of these processes (read in their own namespace)."""
    found: set[Socket] = set()
    for pid in pids:
        try:
            command = " ".join(Path(f"/proc/{pid}/cmdline").read_text().split("\0")).strip()
            inodes = set()
            for fd in os.listdir(f"/proc/{pid}/fd"):
                try:
                    target = os.readlink(f"/proc/{pid}/fd/{fd}")
                except OSError:
                    continue  # closed meanwhile
                match = re.fullmatch(r"socket:\[(\d+)\]", target)
                if match:
                    inodes.add(match[1])
            for table in ("tcp", "tcp6", "udp", "udp6"):
                with open(f"/proc/{pid}/net/{table}") as f:
                    rows = [line.split() for line in f.read().splitlines()[1:]]
                for row in rows:
                    # TCP state 0A: LISTEN; UDP 07: unconnected (bound, takes any datagram)
                    if row[9] in inodes and row[3] == ("0A" if table.startswith("tcp")
                                                      else "07"):
                        address, port = _address(row[1])
                        found.add(Socket(table[:3], address, port, pid, command))
        except FileNotFoundError:
            continue  # the process exited
    return sorted(found, key=lambda s: (s.proto, s.port, s.address))


def namespace_pids(ns: str) -> list[int]:
    return [int(p) for p in ip("netns", "pids", ns).stdout.split()]
