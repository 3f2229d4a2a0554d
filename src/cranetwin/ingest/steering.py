"""Several daemon processes on one UDP address: a ``SO_REUSEPORT`` group whose socket filter
steers each datagram by the machine's wire id, not by its source address.

Without a filter the kernel picks a group member by a hash of the 4-tuple (source and
destination address and port): a machine whose source port changes (a NAT rebinding, a restarted
sender) moves to another process, and closing one member reshuffles unrelated flows. With the
classic BPF program of :func:`steering_program` attached by ``SO_ATTACH_REUSEPORT_CBPF``, the
kernel runs it on each datagram with the UDP payload at offset 0; it loads the wire id (u32, big
endian, bytes 4–7 of the common header in both protocol versions, docs/PROTOCOL.md) and returns
``wire_id % n``: the index of the member socket that receives it. A datagram shorter than 8
bytes aborts the program, which returns 0 (garbage goes to member 0 and is dropped there).

Member indices are the order in which the sockets joined the group (bound). The kernel keeps
the members in an array; when a member socket is *closed*, the last one takes its place, so the
indices of other members change. Hence :func:`bind_group` binds all ``n`` sockets in a fixed
order in one (parent) process, which keeps them open for its whole life and hands socket ``i``
to child ``i``; a child that dies closes only its copy of the descriptor, the socket stays in the
group at index ``i`` and its datagrams queue in that socket's receive buffer until the
restarted child reads them. Binding in the children instead would make the index depend on the
order of (re)starts, and a dead child would remove its socket from the group and move the last
member's machines onto its index.
"""

from __future__ import annotations

import contextlib
import ctypes
import socket
import struct
import sys

from cranetwin.ingest.config import IngestConfigError
from cranetwin.ingest.sockets import _bind_message

__all__ = ["SO_ATTACH_REUSEPORT_CBPF", "WIRE_ID_OFFSET", "attach_steering", "bind_group",
           "steer", "steering_program"]

SO_ATTACH_REUSEPORT_CBPF = getattr(socket, "SO_ATTACH_REUSEPORT_CBPF", 51)  # asm-generic value
WIRE_ID_OFFSET = 4  # bytes 4-7 of the common header: the wire id, u32 big endian
MAX_PROCESSES = 64

# classic BPF opcodes (linux/bpf_common.h)
_BPF_LD_W_ABS = 0x00 | 0x00 | 0x20  # BPF_LD | BPF_W | BPF_ABS: A = u32 at packet offset k
_BPF_ALU_MOD_K = 0x04 | 0x90 | 0x00  # BPF_ALU | BPF_MOD | BPF_K: A %= k
_BPF_RET_A = 0x06 | 0x10  # BPF_RET | BPF_A: return A
_SOCK_FILTER = struct.Struct("=HBBI")  # struct sock_filter {u16 code; u8 jt; u8 jf; u32 k}


def steer(wire_id: int, n: int) -> int:
    """The member index the kernel picks for ``wire_id`` among ``n`` (what the program computes).
    """
    return wire_id % n


def steering_program(n: int, offset: int = WIRE_ID_OFFSET) -> bytes:
    """The classic BPF instructions (``struct sock_filter[3]``, native byte order) returning
    ``u32_be(payload[offset:offset + 4]) % n``.

    Raises:
        ValueError: ``n`` outside 1 … :data:`MAX_PROCESSES`.
    """
    if not 1 <= n <= MAX_PROCESSES:
        raise ValueError(f"steering among {n} sockets: 1 … {MAX_PROCESSES}")
    return b"".join(_SOCK_FILTER.pack(code, 0, 0, k) for code, k in (
        (_BPF_LD_W_ABS, offset), (_BPF_ALU_MOD_K, n), (_BPF_RET_A, 0)))


def attach_steering(sock: socket.socket, n: int) -> None:
    """Attach :func:`steering_program` to the ``SO_REUSEPORT`` group of ``sock`` (any member).

    Raises:
        OSError: the kernel refused it (not Linux ≥ 4.5, or ``sock`` not in a group).
    """
    prog = steering_program(n)
    count = len(prog) // _SOCK_FILTER.size
    buf = ctypes.create_string_buffer(prog, len(prog))
    # struct sock_fprog {unsigned short len; struct sock_filter *filter;} (native alignment)
    fprog = struct.pack("@HP", count, ctypes.addressof(buf))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_REUSEPORT_CBPF, fprog)


def bind_group(host: str, port: int, n: int, rcvbuf_bytes: int = 8 << 20,
               option: str = "--bind") -> list[socket.socket]:
    """``n`` UDP sockets bound to (host, port) with ``SO_REUSEPORT``, in index order, steered by
    wire id (:func:`attach_steering`). Port 0 picks a free port for all of them.

    Returns:
        The sockets; socket ``i`` receives the machines with ``wire_id % n == i``. Keep every
        one open while any member is used (closing one renumbers the others).

    Raises:
        IngestConfigError: not Linux, unresolvable host, non-local address, the port in use
            (by a process that did not set ``SO_REUSEPORT`` or by another user), or the kernel
            refused the filter.
    """
    if not sys.platform.startswith("linux") or not hasattr(socket, "SO_REUSEPORT"):
        raise IngestConfigError("--processes needs Linux (SO_REUSEPORT with a socket filter)")
    if not 1 <= n <= MAX_PROCESSES:
        raise IngestConfigError(f"--processes {n}: 1 … {MAX_PROCESSES}")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        if isinstance(exc, socket.gaierror):
            raise IngestConfigError(_bind_message(exc, host, port, "UDP", option)) from None
        raise IngestConfigError(f"{option}: bad host name {host!r}") from None
    family, socktype, proto, _, addr = infos[0]
    socks: list[socket.socket] = []
    try:
        for _ in range(n):
            sock = socket.socket(family, socktype, proto)
            socks.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
            try:
                sock.bind(addr)
            except OSError as exc:
                raise IngestConfigError(_bind_message(exc, host, port, "UDP", option)) from None
            addr = sock.getsockname()  # port 0: the others join the port the first one got
        try:
            attach_steering(socks[0], n)
        except OSError as exc:
            raise IngestConfigError(f"{option}: the kernel refused the steering filter "
                                    f"(SO_ATTACH_REUSEPORT_CBPF): {exc.strerror or exc}") from None
    except BaseException:
        for s in socks:
            s.close()
        raise
    return socks
