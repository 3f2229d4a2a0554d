"""Several ingest hosts behind a UDP load balancer, on one box: Linux network namespaces.

Four namespaces joined by veth pairs, each name with a random suffix::

    fleet 10.9.3.2 ──► lb 10.9.3.1 ── VIP 10.9.100.1:port, nftables DNAT by
                                      jhash(ip saddr . udp sport) mod 2 → {0: hostA, 1: hostB}
                       lb 10.9.1.1 ──► hostA 10.9.1.2   (default route via lb)
                       lb 10.9.2.1 ──► hostB 10.9.2.2   (default route via lb)
                       lb 10.R.0.2 ──► root  10.R.0.1   (masquerade: hosts reach a root service)

The hosts' replies go back through ``lb``, whose conntrack un-NATs them (an ack comes from the
VIP). Traffic from the hosts to the root namespace is masqueraded to ``lb``'s root-side address,
so the root namespace needs no route. ``lb`` counts datagrams per (wire id, backend) with one nft
counter rule each (the wire id is bytes 4–7 of the UDP payload), so a test can see which host
each machine's datagrams went to. Root and the ``ip``/``nft`` tools are required
(:func:`unavailable_reason`).
"""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field

__all__ = ["HOSTS", "VIP", "Topology", "unavailable_reason"]

VIP = "10.9.100.1"
HOSTS = {"A": "10.9.1.2", "B": "10.9.2.2"}
"""Host name → its address (the daemon listens there, on the VIP's port)."""


def _run(*cmd: str, stdin: str | None = None) -> str:
    out = subprocess.run(cmd, input=stdin, capture_output=True, text=True, timeout=30)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {out.stderr.strip()}")
    return out.stdout


def unavailable_reason() -> str | None:
    """None if namespaces, veth and nftables NAT can be set up here, else why not."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "nft"):
        if shutil.which(tool) is None:
            return f"`{tool}` is not installed"
    name = f"ctprobe{uuid.uuid4().hex[:6]}"
    try:
        _run("ip", "netns", "add", name)
        _run("ip", "netns", "exec", name, "nft", "-f", "-", stdin=(
            "table ip t { chain pre { type nat hook prerouting priority dstnat;\n"
            "udp dport 9 dnat to jhash ip saddr . udp sport mod 2 map "
            "{ 0 : 10.9.1.2, 1 : 10.9.2.2 }; }; }\n"))
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return f"network namespaces with nftables NAT unavailable: {exc}"
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)
    return None


@dataclass
class Topology:
    """The namespaces and links above (:meth:`build`), removed by :meth:`close`.

    Attributes:
        port: UDP port of the VIP and of the daemons.
        wire_ids: Machines whose datagrams ``lb`` counts per backend.
        suffix: Random suffix of every namespace and root-side link name.
        root_ip: Address of the root namespace on its link to ``lb`` (where a root service
            reachable from the hosts listens).
    """

    port: int
    wire_ids: Sequence[int]
    suffix: str = field(default_factory=lambda: uuid.uuid4().hex[:6])
    root_ip: str = ""
    made: list[str] = field(default_factory=list)

    def ns(self, role: str) -> str:
        """Namespace name of ``role`` (fleet, lb, hostA, hostB)."""
        return f"ct{role}{self.suffix}"

    def prefix(self, role: str) -> list[str]:
        """Command prefix that runs a program in ``role``'s namespace."""
        return ["ip", "netns", "exec", self.ns(role)]

    def _in(self, role: str, *cmd: str, stdin: str | None = None) -> str:
        return _run(*self.prefix(role), *cmd, stdin=stdin)

    def build(self) -> Topology:
        """Create namespaces, links, addresses, routes and the balancer's rules (all removed
        again if a step fails)."""
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def _build(self) -> None:
        for role in ("fleet", "lb", "hostA", "hostB"):
            _run("ip", "netns", "add", self.ns(role))
            self.made.append(self.ns(role))
            self._in(role, "ip", "link", "set", "lo", "up")
        for role, net in (("fleet", "10.9.3"), ("hostA", "10.9.1"), ("hostB", "10.9.2")):
            a, b = f"v{role[-1]}l{self.suffix}", f"v{role[-1]}h{self.suffix}"
            _run("ip", "link", "add", a, "netns", self.ns("lb"), "type", "veth", "peer",
                 "name", b, "netns", self.ns(role))
            self._in("lb", "ip", "addr", "add", f"{net}.1/24", "dev", a)
            self._in("lb", "ip", "link", "set", a, "up")
            self._in(role, "ip", "addr", "add", f"{net}.2/24", "dev", b)
            self._in(role, "ip", "link", "set", b, "up")
            self._in(role, "ip", "route", "add", "default", "via", f"{net}.1")
        self._root_link()
        self._in("lb", "sysctl", "-qw", "net.ipv4.ip_forward=1")
        self._in("lb", "nft", "-f", "-", stdin=self._ruleset())

    def _root_link(self) -> None:
        used = _run("ip", "-4", "-o", "addr")
        nets = [n for n in range(100, 250) if f" 10.{n}." not in used]
        net = f"10.{random.choice(nets)}.0"
        root, lb = f"ctr{self.suffix}", f"ctl{self.suffix}"
        _run("ip", "link", "add", root, "type", "veth", "peer", "name", lb, "netns",
             self.ns("lb"))
        self.made.append(root)
        _run("ip", "addr", "add", f"{net}.1/30", "dev", root)
        _run("ip", "link", "set", root, "up")
        self._in("lb", "ip", "addr", "add", f"{net}.2/30", "dev", lb)
        self._in("lb", "ip", "link", "set", lb, "up")
        self.root_ip = f"{net}.1"

    def _ruleset(self) -> str:
        counters = "\n".join(
            f"ip daddr {ip} udp dport {self.port} @th,96,32 {w} counter comment \"w{w}{h}\""
            for w in self.wire_ids for h, ip in HOSTS.items())
        return f"""table ip lb {{
  chain pre {{ type nat hook prerouting priority dstnat;
    {self._balance(list(HOSTS))}
  }}
  chain post {{ type nat hook postrouting priority srcnat;
    oifname "ctl{self.suffix}" masquerade
  }}
  chain count {{ type filter hook forward priority filter;
{counters}
  }}
}}
"""

    def _balance(self, hosts: Sequence[str]) -> str:
        """The DNAT rule: two hash buckets over ``hosts``; a fixed seed, so that a rewritten
        rule hashes every flow as before."""
        ips = [HOSTS[h] for h in hosts]
        buckets = ", ".join(f"{i} : {ips[i % len(ips)]}" for i in range(2))
        return (f"ip daddr {VIP} udp dport {self.port} dnat to jhash ip saddr . udp sport "
                f"mod 2 seed 0x5eed map {{ {buckets} }}")

    def set_backends(self, hosts: Sequence[str]) -> None:
        """Point both hash buckets at ``hosts`` (``["A"]``: host B taken out), atomically.

        As a health checker would, it also drops ``lb``'s conntrack entries of a removed host
        when the ``conntrack`` tool is there; otherwise its flows move once idle for
        ``udp_timeout_s`` (:meth:`short_udp_timeouts`).
        """
        self._in("lb", "nft", "-f", "-", stdin=(
            f"flush chain ip lb pre\nadd rule ip lb pre {self._balance(hosts)}\n"))
        if shutil.which("conntrack"):
            for h, ip in HOSTS.items():
                if h not in hosts:
                    subprocess.run([*self.prefix("lb"), "conntrack", "-D", "--reply-src", ip],
                                   capture_output=True, timeout=30)

    def short_udp_timeouts(self, udp_timeout_s: int = 1) -> None:
        """``lb``'s conntrack forgets an idle UDP flow after ``udp_timeout_s``."""
        for name in ("nf_conntrack_udp_timeout", "nf_conntrack_udp_timeout_stream"):
            self._in("lb", "sysctl", "-qw", f"net.netfilter.{name}={udp_timeout_s}")

    def counts(self) -> dict[int, dict[str, int]]:
        """Datagrams forwarded so far: ``{wire id: {host: n}}``."""
        out: dict[int, dict[str, int]] = {w: dict.fromkeys(HOSTS, 0) for w in self.wire_ids}
        doc = json.loads(self._in("lb", "nft", "-j", "list", "chain", "ip", "lb", "count"))
        for item in doc["nftables"]:
            rule = item.get("rule")
            if not rule or "comment" not in rule:
                continue
            w, h = int(rule["comment"][1:-1]), rule["comment"][-1]
            pkts = next(e["counter"]["packets"] for e in rule["expr"] if "counter" in e)
            out[w][h] = int(pkts)
        return out

    def close(self) -> None:
        """Delete every namespace and root-side link made (their other links go with them)."""
        for name in reversed(self.made):
            if name.startswith("ctr"):
                subprocess.run(["ip", "link", "del", name], capture_output=True, timeout=30)
            else:
                subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)
        self.made.clear()
